"""Store fixtures: ``store`` runs every contract test on the embedded store and on Redis.

``redis_server`` / ``redis_url``: one real redis-server for the whole session (skips when the binary is
absent). ``store`` gives a fresh store per test (Redis: FLUSHDB first, so every test starts empty);
``make_store(**options)`` builds one with options of both stores' constructors (``clock``, ...).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import pytest
from redis_server import RedisServer

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


@pytest.fixture(params=["memory", pytest.param("redis", marks=pytest.mark.redis)])
def store(request: pytest.FixtureRequest) -> MemoryStore | RedisStore:
    if request.param == "memory":
        return MemoryStore()
    return request.getfixturevalue("redis_store")


@pytest.fixture(params=["memory", pytest.param("redis", marks=pytest.mark.redis)])
def make_store(request: pytest.FixtureRequest) -> Iterator[Callable[..., MemoryStore | RedisStore]]:
    made: list[RedisStore] = []

    def make(**options: Any) -> MemoryStore | RedisStore:
        if request.param == "memory":
            return MemoryStore(**options)
        server: RedisServer = request.getfixturevalue("redis_server")
        store = RedisStore(server.url, **options)
        store.client.flushdb()
        made.append(store)
        return store

    yield make
    for store in made:
        store.close()
