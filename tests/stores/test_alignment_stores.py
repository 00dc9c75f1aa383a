"""The device alignment stores (memory, Redis, Redis Cluster) against the same expectations: values kept
exactly per map and device, copies handed out, a map's alignments apart from its objects (``delete_map``
leaves them, ``forget_map`` removes them), and a value this code did not write read as a ``StoreError``."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from redis_server import ADAPTERS, empty_redis_url

from arcloud.errors import StoreError
from arcloud.ports import DeviceAlignments
from arcloud.stores.keys import alignments_key, cluster_slot, map_pattern, meta_key
from arcloud.stores.memory import MemoryStore
from arcloud.stores.memory_alignments import MemoryDeviceAlignments
from arcloud.stores.redis import RedisStore
from arcloud.stores.redis_alignments import RedisDeviceAlignments


@pytest.fixture(params=ADAPTERS)
def adapters(request: pytest.FixtureRequest) -> Iterator[tuple[DeviceAlignments, MemoryStore | RedisStore]]:
    if request.param == "memory":
        yield MemoryDeviceAlignments(), MemoryStore()
        return
    store = RedisStore(empty_redis_url(request))
    yield RedisDeviceAlignments(client=store.client), store
    store.close()


def alignment(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    yaw = rng.uniform(-np.pi, np.pi)
    transform = np.eye(4)
    transform[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    transform[:3, 3] = rng.normal(size=3) * 1e3 + 1e-9  # digits a JSON round trip must keep
    return transform


def test_alignments_are_kept_exactly_per_map_and_device(adapters: tuple[DeviceAlignments, object]) -> None:
    alignments, _ = adapters
    assert alignments.get("kitchen", "phone-1") is None and alignments.of_map("kitchen") == {}
    alignments.put("kitchen", "phone-1", alignment(1))
    alignments.put("kitchen", "phone-2", alignment(2))
    alignments.put("lab", "phone-1", alignment(3))
    got = alignments.get("kitchen", "phone-1")
    assert got is not None and got.dtype == np.float64 and np.array_equal(got, alignment(1))
    got[0, 0] = 7.0  # a copy: the store's value stays
    assert np.array_equal(alignments.get("kitchen", "phone-1"), alignment(1))  # type: ignore[arg-type]  # not None here
    alignments.put("kitchen", "phone-1", alignment(4))  # replaced
    listed = alignments.of_map("kitchen")
    assert sorted(listed) == ["phone-1", "phone-2"] and np.array_equal(listed["phone-1"], alignment(4))
    assert alignments.delete("kitchen", "phone-1") is True and alignments.delete("kitchen", "phone-1") is False
    assert alignments.get("kitchen", "phone-1") is None and sorted(alignments.of_map("kitchen")) == ["phone-2"]
    assert np.array_equal(alignments.get("lab", "phone-1"), alignment(3))  # type: ignore[arg-type]  # not None here


def test_deleting_a_maps_objects_leaves_its_alignments_and_forgetting_the_map_removes_them(
    adapters: tuple[DeviceAlignments, MemoryStore | RedisStore],
) -> None:
    alignments, store = adapters
    alignments.put("kitchen", "phone-1", alignment(1))
    alignments.put("lab", "phone-1", alignment(2))
    store.delete_map("kitchen")
    assert np.array_equal(alignments.get("kitchen", "phone-1"), alignment(1))  # type: ignore[arg-type]  # not None here
    alignments.forget_map("kitchen")
    assert alignments.of_map("kitchen") == {} and alignments.get("lab", "phone-1") is not None
    alignments.forget_map("never-seen")  # nothing to forget: no error


def test_the_redis_key_shares_the_maps_slot_but_not_its_pattern() -> None:
    assert alignments_key("kitchen") == "arcloud:alignments:{kitchen}"
    assert cluster_slot(alignments_key("kitchen")) == cluster_slot(meta_key("kitchen"))
    assert not alignments_key("kitchen").startswith(map_pattern("kitchen").rstrip("*"))


@pytest.mark.redis
def test_a_value_not_written_here_is_a_store_error(redis_url: str) -> None:
    alignments = RedisDeviceAlignments(redis_url)
    try:
        alignments.client.flushdb()
        alignments.client.hset(alignments_key("kitchen"), "phone-1", "[1, 2, 3]")
        with pytest.raises(StoreError, match="the alignment of device phone-1 in map kitchen is not 16 numbers"):
            alignments.get("kitchen", "phone-1")
    finally:
        alignments.close()
