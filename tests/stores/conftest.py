"""Store fixtures: ``store`` runs every contract test on the embedded store, on Redis and on a Redis Cluster.

``redis_server`` / ``redis_url``: one real redis-server for the whole session (skips when the binary is
absent); ``redis_cluster`` (``tests/conftest.py``): one real 3-primary cluster. ``store`` gives a fresh
store per test (Redis: FLUSHDB first, the cluster: FLUSHALL on every node, so every test starts empty);
``make_store(**options)`` builds one with options of both stores' constructors (``clock``, ...).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import pytest
from redis_server import ADAPTERS, LocalCluster, RedisServer, empty_redis_url

from arcloud.stores.memory import MemoryStore
from arcloud.stores.redis import RedisStore


@pytest.fixture(scope="session")
def redis_server() -> Iterator[RedisServer]:
    server = RedisServer.start()
    yield server
    server.stop()


@pytest.fixture(scope="session")
def redis_url(redis_server: RedisServer) -> str:
    return redis_server.url


@pytest.fixture
def redis_store(redis_server: RedisServer) -> Iterator[RedisStore]:
    store = RedisStore(redis_server.url)
    store.client.flushdb()
    yield store
    store.close()


@pytest.fixture
def cluster_store(redis_cluster: LocalCluster) -> Iterator[RedisStore]:
    redis_cluster.flush()
    store = RedisStore(redis_cluster.url)
    yield store
    store.close()


@pytest.fixture(params=ADAPTERS)
def store(request: pytest.FixtureRequest) -> MemoryStore | RedisStore:
    if request.param == "memory":
        return MemoryStore()
    return request.getfixturevalue("redis_store" if request.param == "redis" else "cluster_store")


@pytest.fixture(params=ADAPTERS)
def make_store(request: pytest.FixtureRequest) -> Iterator[Callable[..., MemoryStore | RedisStore]]:
    made: list[RedisStore] = []

    def make(**options: Any) -> MemoryStore | RedisStore:
        if request.param == "memory":
            return MemoryStore(**options)
        store = RedisStore(empty_redis_url(request), **options)
        made.append(store)
        return store

    yield make
    for store in made:
        store.close()
