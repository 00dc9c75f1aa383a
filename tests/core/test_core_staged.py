"""``StagedStore``: a batch of one map's frames integrated one after another and written in one commit ends
as the frames one by one would (a simulated room walked with the simulated detector, on the embedded store),
tells one event per object, records every frame once, and leaves the store as it was when its commit is
refused or when a frame of the batch cannot take its locks."""

from __future__ import annotations

import numpy as np
import pytest

from arcloud.core.change import MapChange
from arcloud.core.staged import StagedStore
from arcloud.core.step import integrate_frame
from arcloud.core.types import Detection, Frame, MapObject, Params
from arcloud.errors import LockTimeout
from arcloud.sim.detector import DetectorFaults, FrameTruths, SimulatedDetector
from arcloud.sim.room import generate_room
from arcloud.sim.sequence import simulate_sequence
from arcloud.stores.memory import MemoryStore

PARAMS = Params()
ROOM_SEED = 3
FRAMES = 36
BATCH = 4


@pytest.fixture(scope="module")
def walk() -> list[tuple[Frame, list[Detection]]]:
    room = generate_room(ROOM_SEED)
    faults = DetectorFaults()
    truths = FrameTruths(room)
    frames = simulate_sequence(room, n_frames=FRAMES, seed=1, faults=faults, truths=truths, device_id="walk")
    detector = SimulatedDetector(room, faults, seed=1, truths=truths)
    return [(frame, detector.detect(frame)) for frame in frames]


def as_compared(obj: MapObject) -> tuple:
    """An object's content: what the step made of it, not how many commits wrote it."""
    assert obj.bounds is not None
    return (
        obj.id,
        obj.label,
        obj.confirmed,
        obj.n_missed,
        obj.n_gone,
        obj.keys.tobytes(),
        obj.weights.tobytes(),
        obj.votes.tobytes(),
        obj.seen_counts.tobytes(),
        obj.bounds.min.tobytes(),
        obj.bounds.max.tobytes(),
    )


def one_by_one(walk: list[tuple[Frame, list[Detection]]]) -> MemoryStore:
    store = MemoryStore()
    for frame, detections in walk:
        integrate_frame(frame, detections, store, PARAMS, now_s=0.0)
    return store


def test_a_batch_ends_as_its_frames_one_by_one(walk: list[tuple[Frame, list[Detection]]]) -> None:
    sequential = one_by_one(walk)
    batched = MemoryStore()
    commits = 0
    for start in range(0, len(walk), BATCH):
        staged = StagedStore(batched, "sim")
        for frame, detections in walk[start : start + BATCH]:
            integrate_frame(frame, detections, staged, PARAMS, now_s=0.0)
        assert staged.flush()
        commits += 1
    expected = sorted(as_compared(o) for o in sequential.list_objects("sim"))
    assert len(expected) >= 4  # the walk made a map worth comparing
    assert sorted(as_compared(o) for o in batched.list_objects("sim")) == expected
    assert batched.count_frames("sim") == sequential.count_frames("sim") == FRAMES
    assert all(batched.is_frame_done("sim", frame.key) for frame, _ in walk)
    # One version a commit: no object is written more than once a batch.
    assert max(o.version for o in batched.list_objects("sim")) <= commits
    assert max(o.version for o in sequential.list_objects("sim")) > commits


def test_a_batch_tells_one_event_per_object_and_its_net_change(walk: list[tuple[Frame, list[Detection]]]) -> None:
    store = one_by_one(walk[:12])
    before = {o.id: o for o in store.list_objects("sim")}
    version = store.changes_since("sim", 0, 10_000).version
    staged = StagedStore(store, "sim")
    for frame, detections in walk[12:20]:
        integrate_frame(frame, detections, staged, PARAMS, now_s=0.0)
    assert staged.flush()
    log = store.changes_since("sim", version, 10)
    assert len(log.entries) == 1  # one commit, one entry
    events = log.entries[0].events
    assert len({e.object_id for e in events}) == len(events)
    after = {o.id: o for o in store.list_objects("sim")}
    for event in events:
        if event.kind == "created":
            assert event.object_id in after and event.object_id not in before
        elif event.kind == "updated":
            assert event.object_id in after and event.object_id in before
            assert after[event.object_id].version == before[event.object_id].version + 1
            assert event.was_confirmed == before[event.object_id].confirmed
        else:
            assert event.object_id in before and event.object_id not in after
    assert {e.object_id for e in events if e.kind in ("created", "updated")} == {
        i for i, o in after.items() if i not in before or o.version != before[i].version
    }


def test_a_refused_flush_writes_nothing_and_frees_the_locks(walk: list[tuple[Frame, list[Detection]]]) -> None:
    store = one_by_one(walk[:8])
    before = sorted((o.id, o.version) for o in store.list_objects("sim"))
    staged = StagedStore(store, "sim")
    for frame, detections in walk[8:12]:
        integrate_frame(frame, detections, staged, PARAMS, now_s=0.0)
    frame, _ = walk[10]
    assert store.commit("sim", [], MapChange(), frame_key=frame.key)  # another worker recorded one of them
    assert not staged.flush()
    assert sorted((o.id, o.version) for o in store.list_objects("sim")) == before
    assert not store.is_frame_done("sim", walk[9][0].key)
    ids = [i for i, _ in before]
    store.lock("sim", ids, ttl_s=5.0, timeout_s=0.0).release()  # the batch's locks were released


def test_a_frame_that_would_wait_for_more_locks_is_left_out(walk: list[tuple[Frame, list[Detection]]]) -> None:
    store = one_by_one(walk[:24])
    for frame, detections in walk[24:]:  # a frame that does not see the whole map
        staged = StagedStore(store, "sim")
        integrate_frame(frame, detections, staged, PARAMS, now_s=0.0)
        others = sorted(set(store.object_ids("sim")) - staged.held)
        if others:
            break
        staged.release()
    else:
        pytest.fail("every frame of the walk locked the whole map")
    busy = store.lock("sim", others, ttl_s=5.0, timeout_s=0.0)
    with pytest.raises(LockTimeout):  # tried once, not waited for
        staged.lock("sim", [*sorted(staged.held), others[0]], ttl_s=5.0, timeout_s=30.0)
    busy.release()
    assert staged.flush()
    assert store.is_frame_done("sim", frame.key)


def test_a_frame_seen_twice_in_a_batch_counts_once(walk: list[tuple[Frame, list[Detection]]]) -> None:
    store = MemoryStore()
    staged = StagedStore(store, "sim")
    frame, detections = walk[0]
    integrate_frame(frame, detections, staged, PARAMS, now_s=0.0)
    again = integrate_frame(frame, detections, staged, PARAMS, now_s=0.0)
    assert again.skipped
    assert staged.flush()
    assert store.count_frames("sim") == 1
    single = one_by_one(walk[:1])
    assert sorted(as_compared(o) for o in store.list_objects("sim")) == sorted(as_compared(o) for o in single.list_objects("sim"))
    assert np.all([o.version == 1 for o in store.list_objects("sim")])
