"""Snapshots (``arcloud.stores.snapshot``) on both stores: voxel colours go through, a snapshot of another codec
version is refused, and a restore refuses, naming the object and the field, what the step could not have stored
(labels, boxes, ids)."""

from __future__ import annotations

import io
import json
import zipfile

import numpy as np
import pytest
from snapshot_edits import with_object_changed, with_object_renamed
from store_cases import MAP, assert_same_object, make_object

from arcloud.core.change import MapChange
from arcloud.core.header import MapHeader
from arcloud.core.types import AABB, OBB, MapObject, Params
from arcloud.core.voxels import keys_bounds
from arcloud.errors import InvalidInput, MapMismatch
from arcloud.stores.memory import MemoryStore
from arcloud.stores.snapshot import read_snapshot, restore_bytes, snapshot_bytes


def test_a_snapshot_carries_the_voxel_colours(store) -> None:
    source = MemoryStore()
    source.open_map(MAP, MapHeader.from_params(Params(), codec_version=source.codec_version, created_at_s=1.0))
    objects = [make_object(1, (0.0, 0.0, 0.0), seed=1), make_object(2, (2.0, 0.0, 0.0), seed=2).replace(colors=None)]
    source.commit(MAP, [], MapChange.writing(MAP, objects))
    assert restore_bytes(store, "copy", snapshot_bytes(source, MAP), params=Params()) == 2
    for got, want in zip(store.list_objects("copy"), objects, strict=True):
        assert_same_object(got, want.replace(version=1))


def a_snapshot(objects: list[MapObject]) -> bytes:
    source = MemoryStore()
    source.open_map(MAP, MapHeader.from_params(Params(), codec_version=source.codec_version, created_at_s=1.0))
    source.commit(MAP, [], MapChange.writing(MAP, objects))
    return snapshot_bytes(source, MAP)


@pytest.mark.parametrize("other", [-1, 1])
def test_a_snapshot_of_another_codec_version_is_refused(store, other: int) -> None:
    data = a_snapshot([make_object(1, (0.0, 0.0, 0.0))])
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        files = {name: archive.read(name) for name in archive.namelist()}
    document = json.loads(files["snapshot.json"])
    document["header"]["codec_version"] = store.codec_version + other
    files["snapshot.json"] = json.dumps(document).encode()
    future = io.BytesIO()
    with zipfile.ZipFile(future, "w") as out:
        for name, content in files.items():
            out.writestr(name, content)
    with pytest.raises(MapMismatch, match="codec_version"):
        restore_bytes(store, MAP, future.getvalue())
    assert store.map_header(MAP) is None and store.list_objects(MAP) == []


def test_a_snapshot_that_unpacks_to_more_than_the_limit_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    from arcloud.errors import InvalidInput
    from arcloud.stores import snapshot

    objects = [make_object(i, (i * 1.0, 0.0, 0.0), seed=i) for i in (1, 2)]
    data = a_snapshot(objects)
    monkeypatch.setattr(snapshot, "MAX_UNPACKED_BYTES", 1000)  # the file's members unpack to a few kB
    with pytest.raises(InvalidInput, match="unpacked"):
        restore_bytes(MemoryStore(), MAP, data, params=Params())


def test_a_snapshot_that_unpacks_to_many_times_its_size_is_refused_and_a_real_maps_is_not() -> None:
    """Below the 1 GiB limit, a 1 MB file unpacking to 1 GB was read whole (a review: three at once, 4.3 GB)."""
    objects = [make_object(i, (i * 1.0, 0.0, 0.0), seed=i) for i in range(1, 40)]
    data = a_snapshot(objects)
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        unpacked = sum(info.file_size for info in archive.infolist())
    assert unpacked < 2 * len(data)  # its blobs are compressed already
    assert restore_bytes(MemoryStore(), MAP, data, params=Params()) == len(objects)
    padded = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(data)) as source, zipfile.ZipFile(padded, "w", zipfile.ZIP_DEFLATED) as target:
        for name in source.namelist():
            target.writestr(name, source.read(name))
        target.writestr("padding", bytes(8 * len(data) + 2**20))  # zeros: a few kB packed
    with pytest.raises(InvalidInput, match=r"at most \d+ bytes unpacked \(8 times its \d+ bytes \+ 1 MiB"):
        restore_bytes(MemoryStore(), MAP, padded.getvalue(), params=Params())


# --- what a snapshot may hold (issue 22: any label was stored and served, a NaN box served as null, an id >= 2**63 a 500)
NAN3 = np.array([np.nan, 0.0, 0.0])
FAR = np.array([50.0, 50.0, 50.0])


def valid_snapshot() -> tuple[bytes, MapObject]:
    source = MemoryStore()
    source.open_map(MAP, MapHeader.from_params(Params(), codec_version=source.codec_version, created_at_s=1.0))
    objects = [make_object(1, (0.0, 0.0, 0.0), seed=1), make_object(2, (2.0, 0.0, 0.0), seed=2)]
    source.commit(MAP, [], MapChange.writing(MAP, objects))
    return snapshot_bytes(source, MAP), objects[0]


def edits(obj: MapObject) -> list[tuple[str, dict[str, object]]]:
    """(the field a refusal names, the change to object 1) for each way an object can be wrong."""
    assert obj.aabb is not None and obj.bounds is not None and obj.obb is not None
    lo, hi = obj.bounds.min, obj.bounds.max
    return [
        ("label", {"label": "<img src=x onerror=alert(1)>\nchair"}),
        ("label", {"label": "unicorn"}),
        ("aabb", {"aabb": AABB(NAN3, obj.aabb.max)}),
        ("aabb", {"aabb": AABB(obj.aabb.max, obj.aabb.min)}),
        ("aabb", {"aabb": AABB(FAR, FAR + 1)}),
        ("bounds", {"bounds": AABB(lo + 0.1, hi)}),  # voxels outside the box the index files it under
        ("bounds", {"bounds": AABB(lo - 1000.0, hi + 1000.0)}),
        ("bounds", {"bounds": AABB(lo, np.array([hi[0], np.inf, hi[2]]))}),
        ("bounds", {"bounds": None}),
        ("obb", {"obb": OBB(NAN3, obj.obb.size, obj.obb.rotation, obj.obb.yaw_rad)}),
        ("obb", {"obb": OBB(FAR, obj.obb.size, obj.obb.rotation, obj.obb.yaw_rad)}),
        ("obb", {"obb": OBB(obj.obb.center, -obj.obb.size, obj.obb.rotation, obj.obb.yaw_rad)}),
        ("obb", {"obb": OBB(obj.obb.center, obj.obb.size + 1e300, obj.obb.rotation, obj.obb.yaw_rad)}),  # meets, reaches far
        ("aabb", {"aabb": AABB(obj.aabb.min - 10.0, obj.aabb.max)}),
        ("score", {"score": float("nan")}),
        ("score", {"score": 1.5}),
        ("label_purity", {"label_purity": -0.1}),
        ("score_sum", {"score_sum": float("inf")}),
        ("n_frames", {"n_frames": -3}),
        ("n_frames", {"n_frames": 10**400}),  # past the largest float: was an OverflowError, a 500
        ("floor_votes", {"floor_votes": {0: 10**400}}),  # a float's range is not enough: every frame then failed
        ("created_at_s", {"created_at_s": 1e308}),  # and every read of the map's objects (a review)
        ("devices", {"devices": frozenset({"phone 1\n<b>"})}),
        ("floor_votes", {"floor_votes": {3: -1}}),
        ("wall_votes", {"wall_votes": {360: (2, 1000)}}),
        ("wall_votes", {"wall_votes": {90: (0, 1000)}}),
        ("apart", {"apart": {2: 0}}),
        ("spanned", {"spanned": {1: 2}}),  # its own id
        ("spanned", {"spanned": {2**53: 1}}),
    ]


@pytest.mark.parametrize("case", range(len(edits(valid_snapshot()[1]))))
def test_a_restore_refuses_an_object_the_step_could_not_have_stored_naming_it(store, case: int) -> None:
    valid, obj = valid_snapshot()
    field, change = edits(obj)[case]
    with pytest.raises(InvalidInput) as refused:
        restore_bytes(store, MAP, with_object_changed(valid, 1, **change), params=Params())
    assert refused.value.field == f"objects/1.{field}", str(refused.value)
    assert str(refused.value).startswith(f"objects/1.{field}: expected ")
    assert store.map_header(MAP) is None and store.list_objects(MAP) == []  # nothing written


@pytest.mark.parametrize("name", [str(2**63), str(2**53), "0", "01", "+1", "1_0", "-1", "1e3", "\u0661", "x"])
def test_a_restore_refuses_an_object_id_out_of_range_or_not_written_as_a_snapshot_writes_it(store, name: str) -> None:
    valid, _ = valid_snapshot()
    with pytest.raises(InvalidInput) as refused:
        restore_bytes(store, MAP, with_object_renamed(valid, 1, name), params=Params())
    assert refused.value.field == f"objects/{name}.id" and f"an object id from 1 to {2**53 - 1}" in str(refused.value)
    assert store.map_header(MAP) is None


def test_the_largest_id_restores_and_the_next_new_id_follows_it(store) -> None:
    valid, _ = valid_snapshot()
    assert restore_bytes(store, MAP, with_object_renamed(valid, 1, str(2**53 - 1)), params=Params()) == 2
    assert sorted(o.id for o in store.list_objects(MAP)) == [2, 2**53 - 1]
    assert list(store.new_ids(MAP, 1)) == [2**53]


def test_a_snapshot_is_of_one_version_when_a_commit_lands_while_its_objects_are_read(store) -> None:
    store.open_map(MAP, MapHeader.from_params(Params(), codec_version=store.codec_version, created_at_s=1.0))
    first, second = make_object(1, (0.0, 0.0, 0.0), seed=1), make_object(2, (2.0, 0.0, 0.0), seed=2)
    store.commit(MAP, [], MapChange.writing(MAP, [first, second]))
    merged = first.replace(keys=np.union1d(first.keys, second.keys))  # as a merge writes it: 2's voxels into 1, 2 gone
    merged = merged.replace(
        weights=np.ones(merged.keys.size, np.float32), votes=np.ones((merged.keys.size, first.votes.shape[1]), np.float32),
        seen=None, colors=None, version=2,
    )  # fmt: skip
    merged = merged.replace(bounds=AABB(*keys_bounds(merged.keys, Params().voxel_size_m)))
    reads = []
    list_objects = store.list_objects

    def torn_read(map_id: str) -> list[MapObject]:  # the first read sees the map before the merge: a batch read early
        before = list_objects(map_id)
        if not reads:
            with store.lock(MAP, [1, 2], ttl_s=10, timeout_s=1) as lease:
                store.commit(MAP, [lease], MapChange.writing(MAP, [merged], [second]))
        reads.append(len(before))
        return before

    store.list_objects = torn_read  # type: ignore[method-assign]  # the store reading as a torn batch would
    try:
        _, _, objects = read_snapshot(snapshot_bytes(store, MAP))
    finally:
        del store.list_objects
    assert reads == [2, 1]  # read again after the commit landed: the merged map, one object
    assert [o.id for o in objects] == [1] and objects[0].keys.size == merged.keys.size


def test_a_snapshot_naming_a_member_twice_is_refused_and_the_map_it_would_replace_kept(store) -> None:
    """zipfile reads the last of a name's members, so the others went unchecked; an object written twice failed the
    restore half-way, after ``replace`` had deleted the map (a 500, the map lost: a fuzzing review)."""
    valid, _ = valid_snapshot()
    assert restore_bytes(store, MAP, valid, params=Params()) == 2
    twice = io.BytesIO()  # object 1's metadata member named objects/2.meta: two objects, as the file says
    with zipfile.ZipFile(io.BytesIO(valid)) as source, zipfile.ZipFile(twice, "w") as target:
        for name in sorted(source.namelist(), key=lambda name: name == "objects/1.meta"):  # the renamed one last
            if name == "objects/1.meta":
                with pytest.warns(UserWarning, match="Duplicate name"):
                    target.writestr("objects/2.meta", source.read(name))
            else:
                target.writestr(name, source.read(name))
    with pytest.raises(InvalidInput, match="expected each member once, got member 'objects/2.meta' more than once"):
        restore_bytes(store, MAP, twice.getvalue(), replace=True, params=Params())
    assert sorted(o.id for o in store.list_objects(MAP)) == [1, 2]  # the stored map as it was


def test_a_long_box_in_a_turned_aligned_frame_is_within_reach_of_its_voxels() -> None:
    """The reach of an ``aabb`` is judged in its own frame: a 9 m counter boxed in a frame turned 45 degrees from the
    world spans 6.6 m by 6.6 m there, which judged in the world reached past its voxels by more than 4 m (a review)."""
    from arcloud.core.boxes import refine
    from arcloud.core.types import CLASSES
    from arcloud.core.voxels import pack_keys
    from arcloud.stores.snapshot import check_object

    turn = np.sqrt(0.5)
    world2aligned = ((turn, -turn, 0.0, 0.0), (turn, turn, 0.0, 0.0), (0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    params = Params(world2aligned=world2aligned)
    i, j, k = np.meshgrid(np.arange(180), np.arange(10), np.arange(15, 25), indexing="ij")  # 9 x 0.5 x 0.5 m
    keys = np.sort(pack_keys(np.stack([i.ravel(), j.ravel(), k.ravel()], 1)))
    votes = np.zeros((keys.size, len(CLASSES)), np.float32)
    votes[:, CLASSES.index("table")] = 1
    weights = np.full(keys.size, 5.0, np.float32)
    counter = refine(MapObject(id=1, keys=keys, weights=weights, votes=votes, seen=weights, n_frames=10), params)
    assert counter.aabb is not None and np.all(counter.aabb.max - counter.aabb.min > [6.0, 6.0, 0.4])
    check_object(counter, MapHeader.from_params(params, codec_version=MemoryStore().codec_version, created_at_s=1.0))
