"""What only the Redis store has: its key layout (one hash tag per map), many processes, server failures,
the large-box fallback of the index, metadata listing."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import redis
from redis.crc import key_slot
from redis_server import free_port
from store_cases import MAP, Clock, make_object, step_frame

from arcloud.core.change import MapChange
from arcloud.core.checks import make_frame
from arcloud.core.step import integrate_frame
from arcloud.core.types import AABB, Params
from arcloud.errors import InvalidInput, StaleLease, StoreUnavailable
from arcloud.ports import QueueLimits
from arcloud.stores import keys
from arcloud.stores.memory import MemoryStore
from arcloud.stores.redis import RedisStore
from arcloud.stores.redis_queue import FrameRecord, RedisFrameQueue

pytestmark = pytest.mark.redis


def all_keys(store: RedisStore) -> set[str]:
    return {k.decode() for k in store.client.scan_iter(count=1000)}


def test_every_key_of_a_map_shares_its_hash_tag(redis_store: RedisStore) -> None:
    store = redis_store
    store.commit(
        MAP, [], MapChange.writing(MAP, [make_object(1, (0.0, 0, 0)), make_object(2, (1.5, -2.0, 0))]), frame_key="dev/f1"
    )
    store.new_ids(MAP, 3)
    lease = store.lock(MAP, [1, 2], ttl_s=10, timeout_s=0)
    claim = store.claim(MAP, [(0, 0, 0)], ttl_s=10, timeout_s=0)
    found = all_keys(store) - {keys.MAPS}  # the list of maps is service-wide (its own slot)
    assert found >= {
        keys.ids_key(MAP),
        keys.processed_key(MAP),
        keys.processed_count_key(MAP),
        keys.bounds_key(MAP),
        keys.meta_key(MAP),
        keys.object_key(MAP, 1),
        keys.lock_key(MAP, 2),
        keys.claim_key(MAP, (0, 0, 0)),
        keys.cell_key(MAP, (1, -2, 0)),
    }
    assert {keys.hash_tag(k) for k in found} == {MAP}
    assert {key_slot(k.encode()) for k in found} == {key_slot(keys.map_prefix(MAP).encode())}
    lease.release()
    claim.release()


def test_delete_map_removes_every_key_of_the_map_and_no_other(redis_store: RedisStore) -> None:
    store = redis_store
    other = MAP + "2"  # a map id that starts with the other one: patterns must not mix them up
    store.commit(other, [], MapChange.writing(other, [make_object(1, (0.0, 0, 0))]), frame_key="dev/f1")
    store.client.set("unrelated", b"1")
    kept = all_keys(store)
    store.commit(MAP, [], MapChange.writing(MAP, [make_object(i, (i * 0.7, 0, 0)) for i in (1, 2, 3)]), frame_key="dev/f1")
    store.new_ids(MAP, 4)
    store.lock(MAP, [1], ttl_s=60, timeout_s=0)  # a lease still alive
    store.claim(MAP, [(9, 9, 9)], ttl_s=60, timeout_s=0)
    assert len(all_keys(store)) > len(kept) + 5
    assert store.delete_map(MAP) == 3
    # the deletion's record stays, for a while; the id counter and the versions for good (a map made again goes on)
    assert all_keys(store) == kept | {
        keys.deletion_key(MAP),
        keys.ids_key(MAP),
        keys.version_key(MAP),
        keys.began_key(MAP),
        keys.published_key(MAP),
    }
    assert store.client.ttl(keys.deletion_key(MAP)) > 0
    assert [o.id for o in store.list_objects(other)] == [1]


def test_a_deletion_counts_each_object_once_when_scan_returns_it_twice(
    redis_store: RedisStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Redis documents that SCAN may return an element more than once (the hash rehashes while the deletion
    # removes its fields): the record must count objects removed, not ids seen.
    store = redis_store
    store.commit(MAP, [], MapChange.writing(MAP, [make_object(i, (i * 0.7, 0, 0)) for i in (1, 2, 3)]), frame_key="dev/f1")
    scan = store.client.hscan_iter

    def scan_twice(name: str, *args: object, **kwargs: object):  # the real SCAN, then its first field again
        fields = list(scan(name, *args, **kwargs))
        yield from fields + fields[:1]

    monkeypatch.setattr(store.client, "hscan_iter", scan_twice)
    assert store.delete_map(MAP) == 3
    deletion = store.map_deletion(MAP)
    assert deletion is not None and (deletion.objects, deletion.objects_removed) == (3, 3)


def test_key_templates() -> None:
    assert keys.map_prefix("m") == "arcloud:{m}"
    assert keys.object_key("m", 7) == "arcloud:{m}:obj:7"
    assert keys.cell_key("m", (-1, 0, 2)) == "arcloud:{m}:cell:-1:0:2"
    assert keys.claim_key("m", (np.int64(3), 4, 5)) == "arcloud:{m}:claim:3:4:5"
    assert keys.hash_tag("arcloud:{m}:lock:1") == "m"
    assert keys.hash_tag("arcloud:{}:x") == "arcloud:{}:x"  # an empty tag does not count
    tag = keys.shard_tag(2, 3)
    shard_keys = [
        keys.ingest_stream(tag),
        keys.ingest_dead_letter_stream(tag),
        keys.ingest_dead_letter_bytes(tag),
        keys.ingest_backlog(tag),
        keys.ingest_stats(tag),
        *(k(tag, "m") for k in (keys.ingest_status_key, keys.ingest_sweep_key, keys.ingest_counts_key)),
    ]
    assert (
        keys.ingest_stream(tag) == "arcloud:ingest:{s2.1}"
        and keys.ingest_counts_key(tag, "m") == "arcloud:ingest:{s2.1}:map:m:counts"
    )
    assert len(set(shard_keys)) == 8 and {keys.hash_tag(k) for k in shard_keys} == {tag}  # one slot: the scripts' keys
    assert not any(k.startswith(keys.map_prefix("")) for k in shard_keys)
    service_wide = (keys.INGEST_SHARDS, keys.INGEST_WORKERS, keys.MAPS, keys.API_KEYS)
    assert {keys.hash_tag(k) for k in service_wide} == set(service_wide)  # no tag: single-key commands only


def test_maps_spread_over_the_shards_the_same_in_every_process() -> None:
    assert [keys.shard_of(m, 3) for m in ("qmap", "walk", "b")] == [0, 1, 2]  # CRC-32, not the salted hash()
    counts = np.bincount([keys.shard_of(f"map-{i}", 4) for i in range(4000)], minlength=4)
    assert counts.min() > 900 and keys.shard_of("anything", 1) == 0


@pytest.mark.parametrize("n_shards", [1, 2, 3, 7, 16, 1024])
def test_each_shards_slot_lies_in_its_share_of_the_slots(n_shards: int) -> None:
    slots = [keys.cluster_slot(keys.ingest_stream(keys.shard_tag(k, n_shards))) for k in range(n_shards)]
    assert [slot * n_shards // keys.CLUSTER_SLOTS for slot in slots] == list(range(n_shards))
    rng = np.random.default_rng(0)
    for key in [keys.object_key("m", 1), "arcloud:ingest", *(f"k{{{rng.integers(1e9)}}}x" for _ in range(200))]:
        assert keys.cluster_slot(key) == key_slot(key.encode())  # redis-py's (and Redis's) CRC-16


def test_a_server_that_is_down_raises_store_unavailable() -> None:
    store = RedisStore(f"redis://127.0.0.1:{free_port()}/0")
    with pytest.raises(StoreUnavailable, match="127.0.0.1"):
        store.ping()
    with pytest.raises(StoreUnavailable):
        store.query_region(MAP, np.zeros(3), np.ones(3))
    with pytest.raises(StoreUnavailable):
        store.commit(MAP, [], MapChange.writing(MAP, [make_object(1, (0.0, 0, 0))]))
    with pytest.raises(StoreUnavailable):
        store.lock(MAP, [1], ttl_s=1, timeout_s=0)
    store.close()
    with pytest.raises(InvalidInput, match="url"):
        RedisStore("http://nowhere")


def test_large_boxes_read_the_bounds_instead_of_cells(redis_server) -> None:
    # A store that falls back beyond 8 cells must answer like the embedded store on random boxes.
    rng = np.random.default_rng(0)
    small = RedisStore(redis_server.url, cell_m=0.5, max_query_cells=8)
    small.client.flushdb()
    reference = MemoryStore(cell_m=0.5)
    objects = [make_object(i, tuple(rng.uniform(-4, 4, 3)), size_m=float(rng.uniform(0.05, 1.5)), seed=i) for i in range(1, 40)]
    for store in (small, reference):
        store.commit(MAP, [], MapChange.writing(MAP, objects))
    for _ in range(60):
        lo = rng.uniform(-5, 5, 3)
        hi = lo + rng.uniform(0, 3, 3)
        got, want = small.query_region(MAP, lo, hi), reference.query_region(MAP, lo, hi)
        assert got.keys() == want.keys()
        for object_id, (b_lo, b_hi) in want.items():
            np.testing.assert_array_equal(got[object_id][0], b_lo)
            np.testing.assert_array_equal(got[object_id][1], b_hi)
    assert small.query_region(MAP, np.full(3, -np.inf), np.full(3, np.inf)).keys() == {o.id for o in objects}
    with pytest.raises(InvalidInput, match="lo"):
        small.query_region(MAP, np.zeros(2), np.ones(3))
    small.close()


def test_commit_checks_leases_belong_to_the_map(redis_store: RedisStore) -> None:
    lease = redis_store.lock("map-b", [1], ttl_s=10, timeout_s=0)
    with pytest.raises(InvalidInput, match="leases"):
        redis_store.commit(MAP, [lease], MapChange())
    lease.release()
    with pytest.raises(InvalidInput, match="bounds"):
        redis_store.commit(MAP, [], MapChange.writing(MAP, [make_object(1, (0.0, 0, 0)).replace(bounds=None)]))
    huge = make_object(1, (0.0, 0, 0)).replace(bounds=AABB(np.zeros(3), np.full(3, 1000.0)))  # a stray voxel 1 km away
    with pytest.raises(InvalidInput, match="index cells"):
        redis_store.commit(MAP, [], MapChange.writing(MAP, [huge]))
    assert redis_store.list_objects(MAP) == []


def test_stale_errors_say_what_failed(redis_store: RedisStore) -> None:
    redis_store.commit(MAP, [], MapChange.writing(MAP, [make_object(1, (0.0, 0, 0))]))
    with pytest.raises(StaleLease, match=r"object 1 written without its lock; nothing written"):
        redis_store.commit(MAP, [], MapChange.writing(MAP, [make_object(1, (0.0, 0, 0), version=2)]))


def test_scripts_are_reloaded_after_a_script_flush(redis_store: RedisStore) -> None:
    redis_store.client.script_flush()
    assert redis_store.commit(MAP, [], MapChange.writing(MAP, [make_object(1, (0.0, 0, 0))]))
    with redis_store.lock(MAP, [1], ttl_s=10, timeout_s=0) as lease:
        # a retried acquire (its reply lost) with the same token succeeds instead of waiting for itself
        assert list(redis_store._scripts["acquire"](keys=lease.keys, args=[lease.token, 10_000])) == [0]


def test_a_shared_client_is_not_closed_by_the_store(redis_server) -> None:
    client = redis.Redis.from_url(redis_server.url)
    with RedisStore(client=client) as store:
        store.ping()
    assert client.ping()
    client.close()


CHILD = """
import json, sys, time
sys.path.insert(0, sys.argv[1])
from store_cases import step_frame
from arcloud.core.checks import make_frame
from arcloud.core.step import integrate_frame
from arcloud.core.types import AABB, Params
from arcloud.stores.redis import RedisStore

url, device = sys.argv[2], int(sys.argv[3])
store = RedisStore(url)
store.client.incr("test:ready")
deadline = time.monotonic() + 30
while not store.client.exists("test:go") and time.monotonic() < deadline:
    time.sleep(0.005)
ids = []
for i in range(3):
    frame, detections = step_frame(device, i)
    integrate_frame(frame, detections, store, Params(lock_timeout_s=20.0))
    ids += store.new_ids("ids-map", 50)
for _ in range(20):
    ids += store.new_ids("ids-map", 5)
print(json.dumps(ids))
"""


@pytest.mark.timeout(90)
def test_two_processes_share_one_map(redis_store: RedisStore, redis_server) -> None:
    cases_dir = str(Path(__file__).parent)
    children = [
        subprocess.Popen(
            [sys.executable, "-c", CHILD, cases_dir, redis_server.url, str(device)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for device in range(2)
    ]
    try:
        deadline = time.monotonic() + 60
        while int(redis_store.client.get("test:ready") or 0) < 2 and time.monotonic() < deadline:
            assert all(c.poll() is None for c in children), (
                children[0].stderr.read() if children[0].poll() else children[1].stderr.read()
            )
            time.sleep(0.02)
        redis_store.client.set("test:go", b"1")
        outputs = [c.communicate(timeout=60) for c in children]
    finally:
        for c in children:
            if c.poll() is None:
                c.kill()
                c.wait()
    assert [c.returncode for c in children] == [0, 0], [err for _, err in outputs]
    ids = [i for out, _ in outputs for i in json.loads(out)]
    assert len(ids) == 2 * (3 * 50 + 20 * 5)
    assert len(set(ids)) == len(ids)
    objects = redis_store.list_objects(MAP)
    assert sorted(o.label for o in objects) == ["chair", "table"]
    assert sum(o.n_frames for o in objects) == 2 * 2 * 3
    assert redis_store.count_frames(MAP) == 6
    frame, _ = step_frame(0, 0)
    assert redis_store.is_frame_done(MAP, frame.key)
    # the step replayed in this process is idempotent
    assert integrate_frame(frame, step_frame(0, 0)[1], redis_store, Params()).skipped


def test_index_cells_hold_exactly_the_current_objects(redis_store: RedisStore) -> None:
    store = redis_store
    a, b = make_object(1, (0.1, 0.1, 0.1)), make_object(2, (0.9, 0.9, 0.0))  # b spans 8 cells
    store.commit(MAP, [], MapChange.writing(MAP, [a, b]))

    def index() -> dict[str, set[int]]:
        cells = store.client.scan_iter(match=keys.cell_key(MAP, (0, 0, 0)).rsplit(":", 3)[0] + ":*")
        return {k.decode().split(":cell:")[1]: {int(i) for i in store.client.smembers(k)} for k in cells}

    assert index() == {"0:0:0": {1, 2}, "1:0:0": {2}, "0:1:0": {2}, "1:1:0": {2}}
    with store.lock(MAP, [1, 2], ttl_s=10, timeout_s=0) as lease:
        store.commit(
            MAP, [lease], MapChange.writing(MAP, [make_object(1, (-0.2, 0.1, 0.1), version=2)], [b])
        )  # now spans x = -0.2..0.1
    assert index() == {"-1:0:0": {1}, "0:0:0": {1}}
    assert store.client.hkeys(keys.bounds_key(MAP)) == [b"1"] and store.client.hkeys(keys.meta_key(MAP)) == [b"1"]


def test_a_maps_frame_records_stay_bounded_in_redis_memory(redis_store: RedisStore) -> None:
    """Queue records and processed marks of 2000 frames take what 200 took: a retention's worth (50 s at a
    frame a second). They once grew 240 bytes a frame for ever (16-character frame keys); now they take
    about 200 bytes a frame settled within the retention."""
    clock = Clock()
    client = redis_store.client
    store = RedisStore(client=client, frame_record_retention_s=50.0, clock=clock)
    queue = RedisFrameQueue(client=client, limits=QueueLimits(frame_record_retention_s=50.0), clock=clock, group="bounded")
    queue.prepare()
    rgb, depth = np.zeros((4, 4, 3), np.uint8), np.ones((4, 4), np.float32)

    def process(frame_ids: range) -> None:
        for i in frame_ids:
            queue.put(
                make_frame(
                    rgb,
                    depth,
                    (4.0, 4.0, 1.5, 1.5),
                    np.eye(4),
                    timestamp_s=i,
                    map_id=MAP,
                    device_id="phone-1",
                    frame_id=f"{i:08d}",
                )
            )
            item = queue.take("c1", block_s=1.0)
            assert item is not None
            assert store.commit(MAP, [], MapChange(), frame_key=item.frame_key)
            queue.ack(item, redelivered=False)
            clock.now_s += 1.0

    def used_bytes() -> int:
        return sum(int(client.memory_usage(k, samples=0) or 0) for k in client.scan_iter(match=keys.map_pattern(MAP)))

    process(range(200))
    after_200 = used_bytes()
    process(range(200, 2000))
    after_2000 = used_bytes()
    print(f"\nmap keys after 200 frames: {after_200} B, after 2000: {after_2000} B (retention 50 frames)")
    assert after_2000 <= 1.1 * after_200
    assert queue.map_counts(MAP) == (2000, 0) and store.count_frames(MAP) == 2000
    assert queue.stats().queued_bytes == 0 and queue.stats().processed == 2000


def test_frame_records_parse_and_those_from_before_the_retention_expire_at_once(redis_store: RedisStore) -> None:
    assert FrameRecord.parse("queued 1700000000000-0") == FrameRecord("queued", entry_id="1700000000000-0")
    assert FrameRecord.parse("processed 1700000000.25") == FrameRecord("processed", settled_at_s=1700000000.25)
    assert FrameRecord.parse("failed 1700000000.25 1700000000000-3 5 delivered 6 times (max 5)") == FrameRecord(
        "failed", settled_at_s=1700000000.25, dead_letter_id="1700000000000-3", deliveries=5, reason="delivered 6 times (max 5)"
    )
    # Written before records carried their time (upgrading): expired, so forgotten, and swept away.
    assert FrameRecord.parse("processed") == FrameRecord("processed", settled_at_s=0.0)
    assert FrameRecord.parse("failed RuntimeError: boom") == FrameRecord("failed", settled_at_s=0.0, reason="RuntimeError: boom")
    client = redis_store.client
    queue = RedisFrameQueue(client=client, group="legacy")
    queue.prepare()
    client.hset(
        keys.ingest_status_key("s0.0", MAP), mapping={"d/old-processed": "processed", "d/old-failed": "failed RuntimeError: boom"}
    )
    client.hset(keys.ingest_counts_key("s0.0", MAP), mapping={"accepted": 2, "failed": 1})
    assert queue.frame_status(MAP, "d/old-processed") is None and queue.failed_frames(MAP, 10) == []
    rgb, depth = np.zeros((4, 4, 3), np.uint8), np.ones((4, 4), np.float32)
    assert queue.put(
        make_frame(rgb, depth, (4.0, 4.0, 1.5, 1.5), np.eye(4), timestamp_s=0, map_id=MAP, device_id="d", frame_id="new")
    )
    assert client.hkeys(keys.ingest_status_key("s0.0", MAP)) == [b"d/new"]  # the sweep dropped both
    assert queue.map_counts(MAP) == (3, 1)
