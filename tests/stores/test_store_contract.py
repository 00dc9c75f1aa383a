"""The ObjectStore contract, run against every adapter: the embedded ``MemoryStore`` and ``RedisStore`` on
a real redis-server (see ``conftest.py``). Both must behave the same."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from store_cases import (
    CHAIR_RGB,
    MAP,
    TABLE_RGB,
    Clock,
    assert_same_object,
    make_object,
    moved,
    run_steps_in_threads,
    step_frame,
)

import arcloud.stores.memory
import arcloud.stores.redis
from arcloud.core.change import MapChange
from arcloud.core.header import MapHeader, check_header
from arcloud.core.ports import MAX_CELLS_PER_CALL
from arcloud.core.step import integrate_frame
from arcloud.core.types import Params
from arcloud.errors import InvalidInput, LockTimeout, MapMismatch, StaleLease, TooManyCells
from arcloud.stores import keys
from arcloud.stores.redis import RedisStore


# --- spatial index -----------------------------------------------------------------------------------
def test_query_region_finds_objects_by_bounds(store) -> None:
    a = make_object(1, (0.1, 0.1, 0.1))  # bounds [0.1, 0.4]^3 (in cell 0,0,0)
    b = make_object(2, (3.0, 3.0, 0.0))  # [3.0, 3.3] x [3.0, 3.3] x [0, 0.3]
    c = make_object(3, (0.9, 0.9, 0.9), size_m=1.3)  # [0.9, 2.2]^3: spans 27 cells
    assert store.commit(MAP, [], MapChange.writing(MAP, [a, b, c]))

    found = store.query_region(MAP, np.array([0.0, 0.0, 0.0]), np.array([0.5, 0.5, 0.5]))
    assert set(found) == {1}
    np.testing.assert_allclose(found[1][0], a.bounds.min)
    np.testing.assert_allclose(found[1][1], a.bounds.max)
    # same index cell as a but outside its bounds: the exact test drops it
    assert store.query_region(MAP, np.array([0.45, 0.45, 0.45]), np.array([0.6, 0.6, 0.6])) == {}
    # touching c's far corner only
    assert set(store.query_region(MAP, np.array([2.2, 2.2, 2.2]), np.array([2.9, 2.9, 2.9]))) == {3}
    assert set(store.query_region(MAP, np.array([-1.0, -1.0, -1.0]), np.array([5.0, 5.0, 5.0]))) == {1, 2, 3}
    assert store.query_region(MAP, np.array([10.0, 10.0, 10.0]), np.array([11.0, 11.0, 11.0])) == {}
    # negative coordinates and an empty map
    assert store.query_region("other-map", np.array([-1.0, -1.0, -1.0]), np.array([5.0, 5.0, 5.0])) == {}
    # a box far larger than the index (many cells): same answer
    assert set(store.query_region(MAP, np.full(3, -150.0), np.full(3, 150.0))) == {1, 2, 3}


def test_query_region_follows_moves_and_deletes(store) -> None:
    a = make_object(1, (0.1, 0.1, 0.1))
    b = make_object(2, (3.0, 3.0, 0.0))
    store.commit(MAP, [], MapChange.writing(MAP, [a, b]))
    here, there = (np.zeros(3), np.full(3, 0.5)), (np.full(3, 5.0), np.full(3, 5.6))
    with store.lock(MAP, [1], ttl_s=10, timeout_s=1) as lease:
        a2 = moved(a, (5.1, 5.1, 5.1))
        assert store.commit(MAP, [lease], MapChange.writing(MAP, [a2]))
    assert store.query_region(MAP, *here) == {}
    assert set(store.query_region(MAP, *there)) == {1}
    np.testing.assert_allclose(store.query_region(MAP, *there)[1][0], a2.bounds.min)
    with store.lock(MAP, [1, 2], ttl_s=10, timeout_s=1) as lease:
        assert store.commit(MAP, [lease], MapChange.writing(MAP, [], [a2]))
    assert store.query_region(MAP, np.full(3, -10.0), np.full(3, 10.0)).keys() == {2}
    assert [o.id for o in store.list_objects(MAP)] == [2]


# --- locks and claims --------------------------------------------------------------------------------
def test_locks_are_exclusive_and_all_or_nothing(store) -> None:
    first = store.lock(MAP, [2, 1], ttl_s=10, timeout_s=0)
    assert first.ids == (1, 2)
    with pytest.raises(LockTimeout):
        store.lock(MAP, [3, 2], ttl_s=10, timeout_s=0)
    # the failed attempt took nothing: 3 is free
    store.lock(MAP, [3], ttl_s=10, timeout_s=0).release()
    # other maps are independent
    store.lock("map-b", [1, 2], ttl_s=10, timeout_s=0).release()
    first.release()
    store.lock(MAP, [1, 2, 3], ttl_s=10, timeout_s=0).release()


def test_lock_timeout_waits_then_gives_up_holding_nothing(store) -> None:
    held = store.lock(MAP, [5], ttl_s=10, timeout_s=0)
    started = time.monotonic()
    with pytest.raises(LockTimeout):
        store.lock(MAP, [4, 5, 6], ttl_s=10, timeout_s=0.2)
    assert 0.2 <= time.monotonic() - started < 2.0
    store.lock(MAP, [4, 6], ttl_s=10, timeout_s=0).release()
    held.release()


def test_lock_waits_for_a_release(store) -> None:
    held = store.lock(MAP, [1], ttl_s=10, timeout_s=0)
    releaser = threading.Timer(0.1, held.release)
    releaser.start()
    started = time.monotonic()
    with store.lock(MAP, [1], ttl_s=10, timeout_s=5) as lease:
        assert lease.ids == (1,)
    assert 0.05 <= time.monotonic() - started < 2.0
    releaser.join()


def test_expired_lock_can_be_taken_and_only_its_owner_releases(store) -> None:
    old = store.lock(MAP, [1], ttl_s=0.1, timeout_s=0)
    started = time.monotonic()
    new = store.lock(MAP, [1], ttl_s=10, timeout_s=2)
    assert time.monotonic() - started >= 0.05
    old.release()  # expired and taken over: must not free the new holder's lock
    with pytest.raises(LockTimeout):
        store.lock(MAP, [1], ttl_s=10, timeout_s=0)
    new.release()
    new.release()  # twice is harmless
    store.lock(MAP, [1], ttl_s=10, timeout_s=0).release()


def test_claims_behave_like_locks(store) -> None:
    claim = store.claim(MAP, [(0, 0, 0), (-1, 2, 3)], ttl_s=10, timeout_s=0)
    assert claim.ids == ()
    with pytest.raises(LockTimeout):
        store.claim(MAP, [(5, 5, 5), (-1, 2, 3)], ttl_s=10, timeout_s=0)
    store.claim(MAP, [(5, 5, 5)], ttl_s=10, timeout_s=0).release()  # nothing kept by the failure
    store.lock(MAP, [0], ttl_s=10, timeout_s=0).release()  # claims and locks do not collide
    claim.release()
    short = store.claim(MAP, [(1, 1, 1)], ttl_s=0.1, timeout_s=0)
    taken = store.claim(MAP, [(1, 1, 1)], ttl_s=10, timeout_s=2)
    short.release()
    with pytest.raises(LockTimeout):
        store.claim(MAP, [(1, 1, 1)], ttl_s=10, timeout_s=0)
    taken.release()


def test_a_claim_takes_at_most_max_cells_per_call(store) -> None:
    cells = [(i, j, k) for i in range(17) for j in range(16) for k in range(16)]  # 4352 > MAX_CELLS_PER_CALL
    started = time.perf_counter()
    with pytest.raises(TooManyCells, match=f"cells: expected at most {MAX_CELLS_PER_CALL} index cells"):
        store.claim(MAP, cells, ttl_s=10, timeout_s=0)
    assert time.perf_counter() - started < 1.0
    store.claim(MAP, cells[:MAX_CELLS_PER_CALL], ttl_s=10, timeout_s=0).release()  # nothing was held


# --- objects and commits -----------------------------------------------------------------------------
def test_commit_and_get_round_trip(store) -> None:
    objects = [make_object(i, (i * 1.0, 0.0, 0.0), seed=i) for i in (3, 1, 2)]
    assert store.commit(MAP, [], MapChange.writing(MAP, objects))
    got = store.get(MAP, [2, 99, 3])
    assert [o.id for o in got] == [2, 3]
    assert_same_object(got[0], objects[2])
    assert_same_object(got[1], objects[0])
    listed = store.list_objects(MAP)
    assert [o.id for o in listed] == [1, 2, 3]
    assert_same_object(listed[0], objects[1])
    assert store.get(MAP, []) == []
    assert store.list_objects("empty-map") == []


def test_voxel_colours_round_trip_and_unknown_ones_stay_unknown(store) -> None:
    coloured, unknown = make_object(1, (0.0, 0.0, 0.0), seed=1), make_object(2, (2.0, 0.0, 0.0), seed=2).replace(colors=None)
    assert coloured.colors is not None and len({tuple(c) for c in coloured.colors}) > 1
    assert store.commit(MAP, [], MapChange.writing(MAP, [coloured, unknown]))
    got_coloured, got_unknown = store.get(MAP, [1, 2])
    assert_same_object(got_coloured, coloured)
    assert_same_object(got_unknown, unknown)  # None: unknown, not a colour


def test_steps_through_the_store_keep_each_objects_colour(store) -> None:
    for index in range(3):
        integrate_frame(*step_frame(0, index), store, Params())
    objects = store.list_objects(MAP)
    assert sorted(o.label for o in objects) == ["chair", "table"]
    for obj in objects:
        assert {tuple(c) for c in obj.colors} == {CHAIR_RGB if obj.label == "chair" else TABLE_RGB}


def test_a_map_created_under_another_codec_version_is_refused(store) -> None:
    store.open_map(MAP, MapHeader.from_params(Params(), codec_version=store.codec_version, created_at_s=1.0))
    check_header(store.map_header(MAP), Params(), codec_version=store.codec_version)
    for other in (store.codec_version - 1, store.codec_version + 1):
        store.open_map(f"map-{other}", MapHeader.from_params(Params(), codec_version=other, created_at_s=1.0))
        with pytest.raises(MapMismatch, match=f"codec_version: map {other}, ours {store.codec_version}"):
            check_header(store.map_header(f"map-{other}"), Params(), codec_version=store.codec_version)


def test_commit_fences_versions_and_locks(store) -> None:
    a = make_object(1, (0.0, 0.0, 0.0))
    store.commit(MAP, [], MapChange.writing(MAP, [a]))
    with pytest.raises(StaleLease):  # an existing object written without its lock
        store.commit(MAP, [], MapChange.writing(MAP, [moved(a, (1.0, 0, 0))]))
    with pytest.raises(StaleLease):  # a "new" object that already exists
        store.commit(MAP, [], MapChange.writing(MAP, [make_object(1, (2.0, 0, 0))]))
    with pytest.raises(StaleLease):  # version 2 of an object that does not exist
        store.commit(MAP, [], MapChange.writing(MAP, [make_object(9, (2.0, 0, 0), version=2)]))
    with store.lock(MAP, [1], ttl_s=10, timeout_s=0) as lease:
        with pytest.raises(StaleLease):  # skips a version
            store.commit(MAP, [lease], MapChange.writing(MAP, [make_object(1, (1.0, 0, 0), version=3)]))
        with pytest.raises(StaleLease):  # deleted at a stale version
            store.commit(MAP, [lease], MapChange.writing(MAP, [], [make_object(1, (0.0, 0, 0), version=0)]))
        assert store.commit(MAP, [lease], MapChange.writing(MAP, [moved(a, (1.0, 0, 0))]))
    assert store.get(MAP, [1])[0].version == 2


def test_expired_holder_cannot_overwrite_newer_data(store) -> None:
    a = make_object(1, (0.0, 0.0, 0.0))
    store.commit(MAP, [], MapChange.writing(MAP, [a]))
    slow = store.lock(MAP, [1], ttl_s=0.1, timeout_s=0)
    slow_read = store.get(MAP, [1])[0]
    time.sleep(0.15)  # the slow worker's lock expires
    with store.lock(MAP, [1], ttl_s=10, timeout_s=1) as fast:
        newer = moved(slow_read, (2.0, 0, 0), seed=11)
        assert store.commit(MAP, [fast], MapChange.writing(MAP, [newer]), frame_key="dev/fast")
    with pytest.raises(StaleLease):
        store.commit(MAP, [slow], MapChange.writing(MAP, [moved(slow_read, (4.0, 0, 0), seed=12)]), frame_key="dev/slow")
    assert_same_object(store.get(MAP, [1])[0], newer)
    assert not store.is_frame_done(MAP, "dev/slow")
    # even with a fresh lock, a write based on the old version is refused
    with store.lock(MAP, [1], ttl_s=10, timeout_s=1) as again, pytest.raises(StaleLease):
        store.commit(MAP, [again], MapChange.writing(MAP, [moved(slow_read, (4.0, 0, 0))]))
    assert_same_object(store.get(MAP, [1])[0], newer)


def test_failed_commit_writes_nothing(store) -> None:
    a = make_object(1, (0.0, 0.0, 0.0))
    b = make_object(2, (1.0, 0.0, 0.0))
    store.commit(MAP, [], MapChange.writing(MAP, [a, b]))
    claim = store.claim(MAP, [(3, 0, 0)], ttl_s=0.1, timeout_s=0)
    with store.lock(MAP, [1, 2], ttl_s=10, timeout_s=0) as lease:
        fresh = make_object(3, (3.0, 0, 0))
        good_update = moved(a, (5.0, 0, 0))
        stale_delete = b.replace(version=7)
        with pytest.raises(StaleLease):
            store.commit(MAP, [lease], MapChange.writing(MAP, [fresh, good_update], [stale_delete]), frame_key="dev/f1")
        time.sleep(0.15)  # the claim expires: the whole commit is refused
        with pytest.raises(StaleLease):
            store.commit(MAP, [lease, claim], MapChange.writing(MAP, [fresh, good_update], [b]), frame_key="dev/f1")
    assert [o.id for o in store.list_objects(MAP)] == [1, 2]
    assert_same_object(store.get(MAP, [1])[0], a)
    assert store.query_region(MAP, np.full(3, 2.9), np.full(3, 6.0)) == {}
    assert not store.is_frame_done(MAP, "dev/f1")
    assert store.count_frames(MAP) == 0


def test_frame_is_recorded_once(store) -> None:
    assert not store.is_frame_done(MAP, "dev/f1")
    assert store.commit(MAP, [], MapChange.writing(MAP, [make_object(1, (0.0, 0, 0))]), frame_key="dev/f1")
    assert store.is_frame_done(MAP, "dev/f1")
    assert not store.is_frame_done("map-b", "dev/f1")
    assert store.commit(MAP, [], MapChange.writing(MAP, [make_object(2, (1.0, 0, 0))]), frame_key="dev/f1") is False
    assert [o.id for o in store.list_objects(MAP)] == [1]
    assert store.commit(MAP, [], MapChange(), frame_key="dev/f2")
    assert store.commit(MAP, [], MapChange())  # no frame: always writes
    assert store.count_frames(MAP) == 2
    assert store.count_frames("map-b") == 0


def test_a_frame_given_up_is_not_written_from_its_entry_and_a_processed_one_is_not_given_up(make_store) -> None:
    """A worker paused past its claim resumes after its frame's queue entry was given up (dead-lettered): its
    commit writes nothing. The frame queued again (another entry) is written once, and then is not given up."""
    clock = Clock()
    store = make_store(frame_record_retention_s=10.0, clock=clock)
    change = MapChange.writing(MAP, [make_object(1, (0.0, 0, 0))])
    assert store.give_up_frame(MAP, "dev/f1", "1-0")
    with pytest.raises(StaleLease, match="dev/f1 of queue entry 1-0 was given up"):
        store.commit(MAP, [], change, frame_key="dev/f1", entry_id="1-0")
    assert store.list_objects(MAP) == [] and store.count_frames(MAP) == 0 and not store.is_frame_done(MAP, "dev/f1")
    assert store.changes_since(MAP, 0, 10).version == 0
    assert store.commit(MAP, [], change, frame_key="dev/f1", entry_id="2-0")  # queued again: another entry
    assert not store.give_up_frame(MAP, "dev/f1", "2-0")  # processed: it stays so
    assert store.commit(MAP, [], MapChange(), frame_key="dev/f2", entry_id="2-0")  # the mark is the entry's alone
    assert store.count_frames(MAP) == 2
    clock.now_s += 10.5  # past the retention, as a processed frame's mark
    assert store.commit(MAP, [], MapChange(), frame_key="dev/f3", entry_id="1-0")


# --- a commit that writes releases its leases ---------------------------------------------------------
def test_a_commit_that_writes_frees_its_locks_and_claims_at_once(store) -> None:
    a = make_object(1, (0.0, 0.0, 0.0))
    assert store.commit(MAP, [], MapChange.writing(MAP, [a]))
    lease = store.lock(MAP, [1, 2], ttl_s=10, timeout_s=0)
    claim = store.claim(MAP, [(3, 0, 0)], ttl_s=10, timeout_s=0)
    change = MapChange.writing(MAP, [moved(a, (1.0, 0, 0)), make_object(3, (3.0, 0, 0))])
    assert store.commit(MAP, [lease, claim], change, frame_key="dev/f1")
    store.lock(MAP, [1, 2], ttl_s=10, timeout_s=0).release()  # nobody released them: the commit did
    store.claim(MAP, [(3, 0, 0)], ttl_s=10, timeout_s=0).release()


def test_a_waiter_takes_the_lock_when_its_holder_commits(store, monkeypatch) -> None:
    monkeypatch.setattr(arcloud.stores.redis, "WAKE_MAX_S", 5.0)  # a Redis waiter that was not woken would wait this long
    a = make_object(1, (0.0, 0.0, 0.0))
    assert store.commit(MAP, [], MapChange.writing(MAP, [a]))
    held = store.lock(MAP, [1], ttl_s=10, timeout_s=0)
    taken: list[tuple[float, int]] = []

    def wait() -> None:
        with store.lock(MAP, [1], ttl_s=10, timeout_s=5):
            taken.append((time.monotonic(), store.get(MAP, [1])[0].version))

    waiter = threading.Thread(target=wait)
    waiter.start()
    time.sleep(0.2)  # the waiter finds the lock busy and blocks
    committed_at = time.monotonic()
    assert store.commit(MAP, [held], MapChange.writing(MAP, [moved(a, (1.0, 0, 0))]))  # no release called
    waiter.join(10)
    assert taken, "the waiter never took the lock"
    ((taken_at, version),) = taken
    assert committed_at <= taken_at < committed_at + 1.0, "woken by the commit, not at the end of a wait"
    assert version == 2  # it sees what the commit wrote


def test_a_commit_that_writes_nothing_leaves_its_leases_held(store) -> None:
    a = make_object(1, (0.0, 0.0, 0.0))
    assert store.commit(MAP, [], MapChange.writing(MAP, [a]), frame_key="dev/f1")
    lease = store.lock(MAP, [1], ttl_s=10, timeout_s=0)
    claim = store.claim(MAP, [(3, 0, 0)], ttl_s=10, timeout_s=0)
    change = MapChange.writing(MAP, [moved(a, (1.0, 0, 0)), make_object(3, (3.0, 0, 0))])
    assert not store.commit(MAP, [lease, claim], change, frame_key="dev/f1")  # recorded before
    with pytest.raises(StaleLease):  # a fence fails
        store.commit(MAP, [lease, claim], MapChange.writing(MAP, [a.replace(version=5)]), frame_key="dev/f2")
    with pytest.raises(LockTimeout):
        store.lock(MAP, [1], ttl_s=10, timeout_s=0)
    with pytest.raises(LockTimeout):
        store.claim(MAP, [(3, 0, 0)], ttl_s=10, timeout_s=0)
    lease.release()  # the caller releases them, as before
    claim.release()
    store.lock(MAP, [1], ttl_s=10, timeout_s=0).release()
    store.claim(MAP, [(3, 0, 0)], ttl_s=10, timeout_s=0).release()


def test_a_release_after_a_commit_that_wrote_frees_nobody_elses_lock(store) -> None:
    a = make_object(1, (0.0, 0.0, 0.0))
    assert store.commit(MAP, [], MapChange.writing(MAP, [a]))
    with store.lock(MAP, [1], ttl_s=10, timeout_s=0) as lease:
        assert store.commit(MAP, [lease], MapChange.writing(MAP, [moved(a, (1.0, 0, 0))]))
        other = store.lock(MAP, [1], ttl_s=10, timeout_s=0)  # taken meanwhile
        lease.release()  # a no-op, and so is the with's exit
    with pytest.raises(LockTimeout):
        store.lock(MAP, [1], ttl_s=10, timeout_s=0)
    other.release()
    store.lock(MAP, [1], ttl_s=10, timeout_s=0).release()


def test_processed_frames_are_remembered_for_the_retention_and_counted_for_ever(make_store) -> None:
    clock = Clock()
    store = make_store(frame_record_retention_s=10.0, clock=clock)
    for i in range(300):
        assert store.commit(MAP, [], MapChange(), frame_key=f"dev/f{i}")
        clock.now_s += 1.0
    assert store.count_frames(MAP) == 300
    if isinstance(store, RedisStore):
        marks = store.client.hlen(keys.processed_key(MAP))
    else:
        marks = len(store._map(MAP).frames)
    assert marks <= 11  # the frames of the last 10 s, not 300
    assert store.is_frame_done(MAP, "dev/f299") and not store.is_frame_done(MAP, "dev/f0")
    assert store.commit(MAP, [], MapChange(), frame_key="dev/f299") is False  # redelivered within the retention: once
    assert store.commit(MAP, [], MapChange(), frame_key="dev/f0")  # past it: as a new frame
    assert store.count_frames(MAP) == 301
    clock.now_s += 10.5  # every mark past the retention, none dropped yet: none counts
    assert not store.is_frame_done(MAP, "dev/f299")
    assert store.commit(MAP, [], MapChange(), frame_key="dev/f299")


def test_misses_are_counted_under_the_lock_once_per_frame_without_a_new_version(store) -> None:
    a = make_object(1, (0.1, 0.1, 0.1))
    assert store.commit(MAP, [], MapChange.writing(MAP, [a]))
    with pytest.raises(StaleLease):
        store.commit(MAP, [], MapChange(misses={1: 1}), frame_key="f1")  # not held
    assert store.get(MAP, [1])[0].n_missed == 0
    with store.lock(MAP, [1], ttl_s=10, timeout_s=1) as lease:
        assert store.commit(MAP, [lease], MapChange(misses={1: 1}), frame_key="f1")
        assert not store.commit(MAP, [lease], MapChange(misses={1: 2}), frame_key="f1")  # re-delivered: nothing
    stored = store.get(MAP, [1])[0]
    assert (stored.n_missed, stored.version) == (1, a.version)
    assert_same_object(stored.replace(n_missed=0), a)
    # A rewrite carries the object's own count.
    with store.lock(MAP, [1], ttl_s=10, timeout_s=1) as lease:
        assert store.commit(MAP, [lease], MapChange.writing(MAP, [stored.replace(version=stored.version + 1, n_missed=7)]))
    assert store.get(MAP, [1])[0].n_missed == 7
    assert store.list_objects(MAP)[0].n_missed == 7


def test_gone_counts_are_kept_like_misses(store) -> None:
    a = make_object(1, (0.1, 0.1, 0.1))
    assert store.commit(MAP, [], MapChange.writing(MAP, [a]))
    with pytest.raises(StaleLease):
        store.commit(MAP, [], MapChange(gone={1: 1}), frame_key="f1")  # not held
    with store.lock(MAP, [1], ttl_s=10, timeout_s=1) as lease:
        assert store.commit(MAP, [lease], MapChange(misses={1: 1}, gone={1: 1}), frame_key="f1")
        assert not store.commit(MAP, [lease], MapChange(gone={1: 2}), frame_key="f1")  # re-delivered: nothing
    with store.lock(MAP, [1], ttl_s=10, timeout_s=1) as lease:  # the commit released the first
        assert store.commit(MAP, [lease], MapChange(misses={1: 2}, gone={1: 2}), frame_key="f2")
    stored = store.get(MAP, [1])[0]
    assert (stored.n_missed, stored.n_gone, stored.version) == (2, 2, a.version)
    with store.lock(MAP, [1], ttl_s=10, timeout_s=1) as lease:  # a rewrite carries the object's own counts
        assert store.commit(MAP, [lease], MapChange.writing(MAP, [stored.replace(version=stored.version + 1, n_gone=0)]))
    assert store.list_objects(MAP)[0].n_gone == 0 and store.list_objects(MAP)[0].n_missed == 2


def test_retired_objects_leave_the_map_for_its_history(make_store) -> None:
    clock = Clock()
    store = make_store(retired_history_s=100.0, clock=clock)
    a, b, c = make_object(1, (0.1, 0.1, 0.1)), make_object(2, (3.0, 3.0, 0.0)), make_object(3, (5.0, 0.0, 0.0))
    assert store.commit(MAP, [], MapChange.writing(MAP, [a, b, c]))
    assert store.retired_objects(MAP) == []
    with pytest.raises(StaleLease):
        store.commit(MAP, [], MapChange(retired=tuple([a])))  # not held
    with store.lock(MAP, [1, 2], ttl_s=10, timeout_s=1) as lease:
        with pytest.raises(StaleLease):
            store.commit(MAP, [lease], MapChange(retired=tuple([a.replace(version=a.version + 1)])))  # not the stored version
        assert store.commit(MAP, [lease], MapChange(retired=tuple([a])), frame_key="f1")
    clock.now_s += 10.0
    with store.lock(MAP, [2], ttl_s=10, timeout_s=1) as lease:  # the commit released the first
        assert store.commit(MAP, [lease], MapChange(retired=tuple([b])), frame_key="f2")
    assert [o.id for o in store.list_objects(MAP)] == [3]
    assert store.query_region(MAP, np.full(3, -1.0), np.full(3, 4.0)) == {}
    history = store.retired_objects(MAP)
    assert [(r.meta.id, r.retired_at_s) for r in history] == [(2, clock.now_s), (1, clock.now_s - 10.0)]  # latest first
    assert history[1].meta.label == a.label and history[1].meta.version == a.version and history[1].meta.n_voxels == a.n_voxels
    assert store.retired_objects("map-b") == []
    clock.now_s += 95.0  # a retired 105 s ago, b 95 s ago
    assert [r.meta.id for r in store.retired_objects(MAP)] == [2]
    assert store.commit(MAP, [], MapChange(), frame_key="f3")  # a commit trims the history
    assert [r.meta.id for r in store.retired_objects(MAP)] == [2]
    assert history_size(store) == 1
    store.delete_map(MAP)
    assert store.retired_objects(MAP) == [] and history_size(store) == 0


def test_the_history_keeps_at_most_its_number_of_objects(make_store, monkeypatch) -> None:
    monkeypatch.setattr(arcloud.stores.memory, "RETIRED_HISTORY_MAX_PER_MAP", 2)
    monkeypatch.setattr(arcloud.stores.redis, "RETIRED_HISTORY_MAX_PER_MAP", 2)
    clock = Clock()
    store = make_store(clock=clock)
    objects = [make_object(i, (i * 1.0, 0.0, 0.0)) for i in (1, 2, 3, 4)]
    assert store.commit(MAP, [], MapChange.writing(MAP, objects))
    for obj in objects[:3]:
        clock.now_s += 1.0
        with store.lock(MAP, [obj.id], ttl_s=10, timeout_s=1) as lease:
            assert store.commit(MAP, [lease], MapChange(retired=tuple([obj])))
    assert [r.meta.id for r in store.retired_objects(MAP)] == [3, 2] and history_size(store) == 2  # the oldest left


def history_size(store) -> int:
    """How many retired objects the store holds for MAP, expired ones not yet dropped included."""
    if isinstance(store, RedisStore):
        return int(store.client.hlen(keys.retired_key(MAP)))
    return len(store._map(MAP).retired)


def test_delete_needs_the_lock_and_removes_the_object(store) -> None:
    a, b = make_object(1, (0.0, 0, 0)), make_object(2, (0.2, 0, 0))
    store.commit(MAP, [], MapChange.writing(MAP, [a, b]))
    with pytest.raises(StaleLease):
        store.commit(MAP, [], MapChange.writing(MAP, [], [a]))
    with store.lock(MAP, [1], ttl_s=10, timeout_s=0) as lease:
        assert store.commit(
            MAP, [lease], MapChange.writing(MAP, [], [a, make_object(42, (9.0, 9, 9))])
        )  # unknown ids are skipped
    assert store.get(MAP, [1, 2])[0].id == 2
    assert set(store.query_region(MAP, np.zeros(3), np.ones(3))) == {2}


def test_new_ids_are_unique_across_threads(store) -> None:
    assert list(store.new_ids(MAP, 0)) == []
    first = list(store.new_ids(MAP, 3))
    assert len(set(first)) == 3 and min(first) >= 1
    results: list[list[int]] = []
    lock = threading.Lock()

    def take() -> None:
        mine = []
        for _ in range(40):
            mine += store.new_ids(MAP, 3)
        with lock:
            results.append(mine)

    threads = [threading.Thread(target=take) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)
    every = first + [i for r in results for i in r]
    assert len(every) == 3 + 6 * 40 * 3
    assert len(set(every)) == len(every)
    assert list(store.new_ids("map-b", 1)) == [1]  # counters are per map


def test_new_ids_cost_the_same_for_any_number(store) -> None:
    """A restore moves the counter past its largest id in one call: no list of that many ids is built."""
    started = time.monotonic()
    many = store.new_ids(MAP, 2**53 - 2)
    assert len(many) == 2**53 - 2 and many[0] == 1 and many[-1] == 2**53 - 2
    assert list(store.new_ids(MAP, 1)) == [2**53 - 1]
    assert time.monotonic() - started < 1.0
    with pytest.raises(InvalidInput, match="n: expected >= 0"):
        store.new_ids(MAP, -1)


def test_delete_map_removes_only_that_map(store) -> None:
    store.commit(MAP, [], MapChange.writing(MAP, [make_object(i, (i * 1.0, 0, 0)) for i in (1, 2, 3)]), frame_key="dev/f1")
    store.commit("map-b", [], MapChange.writing("map-b", [make_object(1, (0.0, 0, 0))]), frame_key="dev/f1")
    store.new_ids(MAP, 5)
    assert store.delete_map(MAP) == 3
    assert store.list_objects(MAP) == []
    assert store.query_region(MAP, np.full(3, -5.0), np.full(3, 5.0)) == {}
    assert not store.is_frame_done(MAP, "dev/f1") and store.count_frames(MAP) == 0
    assert [o.id for o in store.list_objects("map-b")] == [1]
    assert store.is_frame_done("map-b", "dev/f1")
    assert store.delete_map("never-made") == 0


def test_a_map_made_again_never_gives_an_id_the_deleted_map_gave(store) -> None:
    """Readers hold objects by id (a Zenoh subscriber, the publisher's ``ServedRouter``): an id of the deleted map
    given again to another object was taken for the old one (the router dropped the new object's first states)."""
    assert list(store.new_ids(MAP, 3)) == [1, 2, 3]
    store.commit(MAP, [], MapChange.writing(MAP, [make_object(i, (i * 1.0, 0, 0)) for i in (1, 2, 3)]))
    store.delete_map(MAP)
    assert list(store.new_ids(MAP, 2)) == [4, 5]
    assert list(store.new_ids("never-made", 1)) == [1]


def test_a_deletion_is_recorded_as_done_with_the_objects_it_removed(store) -> None:
    store.commit(MAP, [], MapChange.writing(MAP, [make_object(i, (i * 1.0, 0, 0)) for i in (1, 2, 3)]), frame_key="dev/f1")
    assert store.map_deletion(MAP) is None
    assert store.delete_map(MAP) == 3
    deletion = store.map_deletion(MAP)
    assert deletion is not None and deletion.done and deletion.map_id == MAP
    assert (deletion.objects, deletion.objects_removed) == (3, 3)
    assert deletion.started_at_s <= deletion.updated_at_s == deletion.finished_at_s
    assert store.map_deletion("map-b") is None


def test_the_first_header_of_a_map_stays_until_the_map_is_deleted(store) -> None:
    first = MapHeader.from_params(Params(), codec_version=2, created_at_s=1.0)
    other = MapHeader.from_params(Params(voxel_size_m=0.04), codec_version=2, created_at_s=2.0)
    assert store.map_header(MAP) is None
    assert store.open_map(MAP, first) == first
    assert store.open_map(MAP, other) == first  # the map keeps the settings it was written under
    assert store.map_header(MAP) == first and store.map_header("map-b") is None
    store.delete_map(MAP)
    assert store.map_header(MAP) is None
    assert store.open_map(MAP, other) == other


def test_concurrent_first_opens_agree_on_one_header(store) -> None:
    headers = [
        MapHeader.from_params(Params(voxel_size_m=0.05 + i / 100), codec_version=2, created_at_s=float(i)) for i in range(8)
    ]
    got: list[MapHeader] = []
    threads = [threading.Thread(target=lambda h=h: got.append(store.open_map(MAP, h))) for h in headers]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(got) == 8 and len(set(got)) == 1 and got[0] in headers


@pytest.mark.timeout(60)
def test_concurrent_first_sightings_make_one_object(store) -> None:
    # Two workers see the same two new objects at the same moment. The space claim serialises the
    # creations and the second worker fuses into what the first created. (With more workers, one may
    # hold the new object's lock while another creates under the claim: a duplicate that the merge
    # pass removes later; the next test covers that end state.)
    params = Params(lock_timeout_s=20.0)
    run_steps_in_threads(store, [[step_frame(d, 0)] for d in range(2)], params)
    objects = store.list_objects(MAP)
    assert sorted(o.label for o in objects) == ["chair", "table"]
    assert [o.n_frames for o in objects] == [2, 2]
    assert all(o.devices == {"dev-0", "dev-1"} for o in objects)


@pytest.mark.timeout(60)
def test_concurrent_steps_lose_no_update_and_leave_no_duplicate(store) -> None:
    n_threads, n_frames = 4, 3
    params = Params(lock_timeout_s=20.0)
    jobs = [[step_frame(d, i) for i in range(n_frames)] for d in range(n_threads)]
    run_steps_in_threads(store, jobs, params)
    objects = store.list_objects(MAP)
    assert sorted(o.label for o in objects) == ["chair", "table"]  # no duplicate left
    assert sum(o.n_frames for o in objects) == 2 * n_threads * n_frames  # no lost update
    assert {d for o in objects for d in o.devices} == {f"dev-{d}" for d in range(n_threads)}
    assert store.count_frames(MAP) == n_threads * n_frames


# --- what the service reads --------------------------------------------------------------------------
def test_metadata_listing_matches_the_objects(store) -> None:
    objects = [make_object(i, (i * 1.0, 0, 0), seed=i) for i in (4, 2)]
    store.commit(MAP, [], MapChange.writing(MAP, objects))
    metas = store.list_meta(MAP)
    assert [m.id for m in metas] == [2, 4]
    for meta, obj in zip(metas, objects[::-1]):
        assert (meta.label, meta.score, meta.version, meta.n_voxels, meta.n_frames, meta.devices, meta.confirmed) == (
            obj.label,
            obj.score,
            obj.version,
            obj.n_voxels,
            obj.n_frames,
            obj.devices,
            obj.confirmed,
        )
        np.testing.assert_array_equal(meta.aabb.min, obj.aabb.min)
    assert [m.id for m in store.object_meta(MAP, [4, 99])] == [4]
    assert store.list_meta("empty-map") == [] and store.object_meta(MAP, []) == []


def test_object_ids_are_the_maps_ids_in_order_and_follow_its_changes(store) -> None:
    objects = [make_object(i, (i * 1.0, 0, 0), seed=i) for i in (12, 3, 7)]
    store.commit(MAP, [], MapChange.writing(MAP, objects))
    assert store.object_ids(MAP) == [3, 7, 12] and store.object_ids("empty-map") == []
    with store.lock(MAP, [7], ttl_s=10, timeout_s=1) as lease:
        store.commit(MAP, [lease], MapChange.writing(MAP, [], [objects[2]]))
    assert store.object_ids(MAP) == [3, 12]


def test_a_reachable_store_answers_its_health_check(store) -> None:
    assert store.ping() is None


def test_opened_maps_are_listed_with_their_last_change_until_deleted(store) -> None:
    header = MapHeader.from_params(Params(), codec_version=2, created_at_s=1000.0)
    assert store.list_maps() == {}
    store.open_map(MAP, header)
    store.open_map("map-b", header)
    assert store.list_maps() == {MAP: 1000.0, "map-b": 1000.0}  # opened, nothing written yet
    assert store.count_objects(MAP) == 0 and store.count_objects("never-made") == 0
    before = time.time()
    store.commit(MAP, [], MapChange.writing(MAP, [make_object(i, (i * 1.0, 0, 0)) for i in (1, 2)]))
    listed = store.list_maps()
    assert before <= listed[MAP] <= time.time() and listed["map-b"] == 1000.0
    assert store.count_objects(MAP) == 2
    store.open_map(MAP, header)  # opening again changes nothing
    assert store.list_maps()[MAP] == listed[MAP]
    store.delete_map(MAP)
    assert store.list_maps() == {"map-b": 1000.0} and store.count_objects(MAP) == 0


@pytest.mark.parametrize(
    ("setting", "value"),
    [("cell_m", 0.0), ("change_log_entries", 0), ("frame_record_retention_s", -1.0), ("retired_history_s", 0.0)],
)
def test_a_store_refuses_settings_it_cannot_keep(make_store, setting, value) -> None:
    with pytest.raises(InvalidInput, match=setting):
        make_store(**{setting: value})
