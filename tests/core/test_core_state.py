"""Explicit state in the step: frozen map objects, change tracking by id, no hidden caches."""

import dataclasses
import pickle
from pathlib import Path

import numpy as np
import pytest
from handmade_frames import two_box_frame

import arcloud.core
from arcloud.core.fusion import fuse_detection, new_object
from arcloud.core.step import diff_with_stored, integrate_frame, merge_duplicates, refine_changed, resolve_shared_voxels
from arcloud.core.types import CLASS_INDEX, N_CLASSES, MapObject, Params, VoxelDetection, empty_object
from arcloud.core.voxels import pack_keys
from arcloud.stores.memory import MemoryStore

PARAMS = Params(voxel_size_m=0.05)


def block(lo, hi):
    grid = np.stack(np.meshgrid(*(np.arange(a, b) for a, b in zip(lo, hi)), indexing="ij"), -1).reshape(-1, 3)
    return np.unique(pack_keys(grid))


def observed(object_id, label, keys, frames=3):
    obj = new_object(object_id, VoxelDetection(CLASS_INDEX[label], 0.9, keys), "dev", 1.0)
    for _ in range(frames - 1):
        obj = fuse_detection(obj, VoxelDetection(CLASS_INDEX[label], 0.9, keys), "dev")
    return obj


# --- frozen map objects -----------------------------------------------------------------------------
def test_a_map_object_cannot_be_edited_in_place():
    obj = observed(1, "chair", block((0, 0, 0), (3, 3, 3)))
    with pytest.raises(dataclasses.FrozenInstanceError):
        obj.score = 1.0  # type: ignore[misc]  # on purpose: frozen
    for array in (obj.keys, obj.weights, obj.votes, obj.seen):
        assert not array.flags.writeable
        with pytest.raises(ValueError, match="read-only"):
            array[0] = 0


def test_replace_agrees_with_dataclasses_replace():
    rng = np.random.default_rng(0)
    names = [f.name for f in dataclasses.fields(MapObject)]
    base = observed(7, "table", block((0, 0, 0), (4, 3, 2)))
    for _ in range(200):
        n = int(rng.integers(4, 12))
        values = {
            "id": int(rng.integers(1, 100)),
            "n_frames": int(rng.integers(0, 9)),
            "score": float(rng.random()),
            "label": str(rng.choice(["chair", "tv", ""])),
            "confirmed": bool(rng.integers(2)),
            "version": int(rng.integers(9)),
            "keys": np.sort(rng.choice(10**6, n, replace=False)).astype(np.int64),
            "weights": rng.random(n, np.float32),
            "votes": rng.random((n, N_CLASSES), np.float32),
            "seen": rng.random(n, np.float32) if rng.integers(2) else None,
            "floor_votes": {int(rng.integers(-3, 3)): 1},
            "wall_votes": {int(rng.integers(0, 360)): (1, int(rng.integers(-3000, 3000)))},
            "devices": frozenset({"a", str(rng.integers(3))}),
        }
        chosen = rng.choice(list(values), int(rng.integers(0, len(values))), replace=False)
        changes = {name: values[name] for name in chosen}
        fast, plain = base.replace(**changes), dataclasses.replace(base, **changes)
        for name in names:
            a, b = getattr(fast, name), getattr(plain, name)
            assert np.array_equal(a, b) if isinstance(a, np.ndarray) else a == b, name
        assert all(
            not a.flags.writeable for a in (fast.keys, fast.weights, fast.votes) + ((fast.seen,) if fast.seen is not None else ())
        )
        base = fast


def test_replace_refuses_a_name_that_is_no_field():
    with pytest.raises(AttributeError):
        empty_object(1).replace(colour="red")


# --- change tracking by id --------------------------------------------------------------------------
def test_objects_equal_to_what_was_read_are_not_written_whatever_their_identity():
    stored = {1: observed(1, "chair", block((0, 0, 0), (3, 3, 3)))}
    copies = [o.replace() for o in stored.values()]  # another instance, same values
    assert refine_changed(copies, set(), set(), PARAMS) == []
    assert diff_with_stored([], stored, {}, "m", 2.0) == ([], [], [])


def test_only_changed_objects_are_refined_and_rescored_ones_written_as_they_are():
    a, b, c = (observed(i, "chair", block((10 * i, 0, 0), (10 * i + 3, 3, 3))) for i in (1, 2, 3))
    written = refine_changed([a, b, c], voxels_changed={1}, rescored={2}, params=PARAMS)
    assert [o.id for o in written] == [1, 2]
    assert written[0].aabb is not None and written[0].label == "chair"  # refined
    assert written[1] is b and b.aabb is None  # rescored: as it is


def test_an_object_that_gives_up_voxels_is_reported_trimmed():
    shared = block((0, 0, 0), (2, 2, 2))
    strong = observed(1, "chair", np.union1d(shared, block((2, 0, 0), (4, 2, 2))), frames=3)
    weak = observed(2, "table", np.union1d(shared, block((-2, 0, 0), (0, 2, 2))), frames=1)
    resolved, trimmed = resolve_shared_voxels([strong, weak])
    assert trimmed == {2}
    assert resolved[0] is strong and resolved[1].keys.size == weak.keys.size - shared.size


def test_merging_reports_the_absorbed_and_their_keeper():
    keys = block((0, 0, 0), (5, 5, 5))
    old, new = observed(1, "tv", keys, frames=4), observed(2, "tv", keys[10:], frames=1)
    kept, absorbed_into = merge_duplicates([old, new], voxels_changed={2}, params=PARAMS)
    assert absorbed_into == {2: 1} and [o.id for o in kept] == [1] and kept[0].n_frames == 5
    assert merge_duplicates([old, new], voxels_changed=set(), params=PARAMS)[1] == {}  # unchanged pairs were checked before


def test_the_diff_bumps_versions_and_names_what_was_deleted_or_merged():
    stored = {
        1: observed(1, "chair", block((0, 0, 0), (3, 3, 3))).replace(version=4, confirmed=True),
        2: observed(2, "tv", block((9, 0, 0), (12, 3, 3))).replace(version=2),
        3: observed(3, "tv", block((20, 0, 0), (23, 3, 3))).replace(version=7),
    }
    updated = stored[1].replace(score=0.5)
    emptied = stored[2].replace(
        keys=np.empty(0, np.int64),
        weights=np.empty(0, np.float32),
        votes=np.empty((0, N_CLASSES), np.float32),
        seen=np.empty(0, np.float32),
    )
    created = observed(9, "chair", block((30, 0, 0), (33, 3, 3)))
    upserts, removed, events = diff_with_stored([updated, emptied, created], stored, {3: 9}, "m", 5.0)
    assert [(o.id, o.version, o.updated_at_s) for o in upserts] == [(1, 5, 5.0), (9, 1, 5.0)]
    assert [o.id for o in removed] == [2, 3] and removed[1] is stored[3]
    assert [(e.kind, e.object_id, e.merged_into, e.was_confirmed) for e in events] == [
        ("updated", 1, None, True),
        ("deleted", 2, None, False),
        ("created", 9, None, False),
        ("merged", 3, 9, False),
    ]


def test_a_frame_writes_what_it_changed_and_counts_a_miss_of_the_rest():
    store = MemoryStore()
    for i in range(3):
        frame, detections = two_box_frame(f"f{i}")
        integrate_frame(frame, detections, store, PARAMS)
    versions = {o.label: o.version for o in store.list_objects("m")}
    frame, detections = two_box_frame("chair-only")
    result = integrate_frame(frame, detections[:1], store, PARAMS)
    after = {o.label: o for o in store.list_objects("m")}
    chair_id, table_id = after["chair"].id, after["table"].id
    assert chair_id in result.updated and after["chair"].version == versions["chair"] + 1
    assert after["table"].n_missed == 1 and after["table"].n_frames == 3
    assert (table_id in result.updated) == (after["table"].version == versions["table"] + 1)


# --- no hidden state --------------------------------------------------------------------------------
def test_params_derive_gravity_once_read_only_and_again_on_replace():
    params = Params(up=(0.0, -1.0, 0.0))
    rotation = params.gravity.world2gravity
    assert np.allclose(rotation @ [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]) and not params.gravity.is_identity
    assert not rotation.flags.writeable and params.gravity is params.gravity
    assert params.replace(up=(0.0, 0.0, 1.0)).gravity.is_identity
    copied = pickle.loads(pickle.dumps(params))
    assert copied == params and np.array_equal(copied.gravity.world2gravity, rotation)
    assert "gravity" not in {f.name for f in dataclasses.fields(Params)}  # derived, not a setting


def test_core_keeps_no_module_level_caches():
    sources = {p.name: p.read_text() for p in Path(arcloud.core.__file__).parent.glob("*.py")}
    for name, text in sources.items():
        for marker in ("lru_cache", "functools.cache", "@cache"):
            assert marker not in text, f"core/{name} uses {marker}"
