"""Snapshots (``arcloud.stores.snapshot``) on both stores: voxel colours go through, and a snapshot taken
before colours (codec version 2) still restores, its colours unknown."""

from __future__ import annotations

import io
import json
import zipfile

import numpy as np
import pytest
from store_cases import MAP, assert_same_object, make_object

from arcloud.core.header import MapHeader
from arcloud.core.types import MapObject, Params
from arcloud.errors import MapMismatch
from arcloud.stores import codec
from arcloud.stores.memory import MemoryStore
from arcloud.stores.snapshot import FORMAT, restore_bytes, snapshot_bytes


def version_2_blob(obj: MapObject) -> bytes:
    """The object's voxels as codec version 2 wrote them (its layout, spelled out here): no colours."""
    assert obj.seen is not None
    payload = (np.diff(obj.keys, prepend=0).astype("<i8"), obj.weights, obj.seen, obj.votes)
    return codec._HEADER.pack(b"ARCV", 2, 0, obj.votes.shape[1], obj.keys.size) + b"".join(a.tobytes() for a in payload)


def version_2_snapshot(objects: list[MapObject]) -> bytes:
    """A snapshot file as the service wrote it under codec version 2."""
    header = MapHeader.from_params(Params(), codec_version=2, created_at_s=1.0)
    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w") as out:
        document = {"format": FORMAT, "map_id": MAP, "header": header.to_record(), "codec_version": 2, "objects": len(objects)}
        out.writestr("snapshot.json", json.dumps(document))
        for obj in objects:
            out.writestr(f"objects/{obj.id}.meta", codec.encode_meta(obj))
            out.writestr(f"objects/{obj.id}.voxels", version_2_blob(obj))
    return archive.getvalue()


def test_a_snapshot_carries_the_voxel_colours(store) -> None:
    source = MemoryStore()
    source.open_map(MAP, MapHeader.from_params(Params(), codec_version=source.codec_version, created_at_s=1.0))
    objects = [make_object(1, (0.0, 0.0, 0.0), seed=1), make_object(2, (2.0, 0.0, 0.0), seed=2).replace(colors=None)]
    source.commit(MAP, [], objects, [])
    assert restore_bytes(store, "copy", snapshot_bytes(source, MAP), params=Params()) == 2
    for got, want in zip(store.list_objects("copy"), objects, strict=True):
        assert_same_object(got, want.replace(version=1))


def test_a_snapshot_taken_before_colours_restores_with_colours_unknown(store) -> None:
    objects = [make_object(i, (i * 1.0, 0.0, 0.0), seed=i) for i in (1, 2)]
    assert restore_bytes(store, MAP, version_2_snapshot(objects), params=Params()) == 2
    for got, want in zip(store.list_objects(MAP), objects, strict=True):
        assert got.colors is None
        assert_same_object(got, want.replace(version=1, colors=None))
    # The objects were written again in the store's format: the map's header says so.
    assert store.map_header(MAP).codec_version == store.codec_version
    assert restore_bytes(store, MAP, snapshot_bytes(store, MAP), replace=True, params=Params()) == 2


def test_a_snapshot_of_a_codec_version_the_store_cannot_read_is_refused(store) -> None:
    data = version_2_snapshot([make_object(1, (0.0, 0.0, 0.0))])
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        files = {name: archive.read(name) for name in archive.namelist()}
    document = json.loads(files["snapshot.json"])
    document["header"]["codec_version"] = store.codec_version + 1
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
    data = version_2_snapshot(objects)
    monkeypatch.setattr(snapshot, "MAX_UNPACKED_BYTES", 1000)  # the file's members unpack to a few kB
    with pytest.raises(InvalidInput, match="unpacked"):
        restore_bytes(MemoryStore(), MAP, data, params=Params())
