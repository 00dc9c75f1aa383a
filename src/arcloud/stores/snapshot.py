"""A map as one file, and back into any ``ObjectStore`` (embedded or Redis): ``arcloud maps snapshot |
restore | copy`` and the API's ``/v1/maps/{map}/snapshot``.

The file is a zip: ``snapshot.json`` (``format``, the map id it was taken of, its header, the codec
version, the object count) and, per object, ``objects/<id>.meta`` (``codec.encode_meta``) and
``objects/<id>.voxels`` (``codec.encode_voxels``), so a restore is exact: ids, labels, scores, boxes,
status, every voxel's weight, votes, sightings and colour. Only the versions (the stores' write fences) start
again at 1. A restore writes into an empty map (or replaces the map, when asked) under the snapshot's header
(its codec version: the store's own, in which the objects are written again; a snapshot taken under an older
codec version restores, its colours unknown), keeps the ids and moves the map's id counter past them.
"""

from __future__ import annotations

import dataclasses
import io
import json
import zipfile
import zlib

from arcloud.core.header import MapHeader, check_header
from arcloud.core.types import MapObject, Params
from arcloud.errors import InvalidInput, MapMismatch, StoreError
from arcloud.ports import ObjectStore
from arcloud.stores import codec

FORMAT = "arcloud.snapshot.v1"
RESTORE_BATCH = 256  # objects per commit
MAX_UNPACKED_BYTES = 2**30  # a snapshot whose members unpack to more is refused (zip bombs); a real map is a few MB
# What reading a malformed file raises: zipfile's own errors, a corrupt deflate stream (zlib.error), a member
# name outside objects/ (IndexError), an encrypted or oddly compressed member (RuntimeError, NotImplementedError),
# JSON nested too deep (RecursionError), a blob the codec refuses (StoreError: here the file's fault, not a store's).
UNREADABLE = (
    zipfile.BadZipFile,
    zipfile.LargeZipFile,
    zlib.error,
    EOFError,
    KeyError,
    IndexError,
    ValueError,
    TypeError,
    RuntimeError,
    StoreError,
)


def snapshot_bytes(store: ObjectStore, map_id: str) -> bytes:
    """The map's header and objects as a snapshot file's bytes (``InvalidInput`` for a map never opened)."""
    header = store.map_header(map_id)
    if header is None:
        raise InvalidInput("map_id", "a map with data", repr(map_id))
    objects = store.list_objects(map_id)
    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as out:
        document = {
            "format": FORMAT,
            "map_id": map_id,
            "header": header.to_record(),
            "codec_version": codec.FORMAT_VERSION,
            "objects": len(objects),
        }
        out.writestr("snapshot.json", json.dumps(document, indent=1))
        for obj in objects:
            out.writestr(f"objects/{obj.id}.meta", codec.encode_meta(obj))
            out.writestr(
                f"objects/{obj.id}.voxels",
                codec.encode_voxels(obj.keys, obj.weights, obj.votes, seen=obj.seen, colors=obj.colors),
            )
    return archive.getvalue()


def read_snapshot(data: bytes) -> tuple[dict[str, object], MapHeader, list[MapObject]]:
    """(its description, header, objects); ``InvalidInput`` naming what is wrong with the file."""
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            unpacked = sum(info.file_size for info in archive.infolist())  # zipfile reads no member past its size
            if unpacked > MAX_UNPACKED_BYTES:
                raise InvalidInput("snapshot", f"at most {MAX_UNPACKED_BYTES} bytes unpacked", f"{unpacked} bytes")
            document = json.loads(archive.read("snapshot.json"))
            if not isinstance(document, dict) or document.get("format") != FORMAT:
                raise InvalidInput(
                    "snapshot", f"a {FORMAT} file", f"format {document.get('format') if isinstance(document, dict) else None!r}"
                )
            header = MapHeader.from_record(document["header"])
            ids = sorted(int(name.split("/")[1].removesuffix(".meta")) for name in archive.namelist() if name.endswith(".meta"))
            objects = [
                codec.decode_object(i, archive.read(f"objects/{i}.meta"), archive.read(f"objects/{i}.voxels")) for i in ids
            ]
    except UNREADABLE as exc:
        raise InvalidInput("snapshot", f"a {FORMAT} zip file", f"one that cannot be read ({type(exc).__name__}: {exc})") from exc
    if len(objects) != document.get("objects"):
        raise InvalidInput("snapshot", f"{document.get('objects')} objects, as it says", f"{len(objects)}")
    return document, header, objects


def restore_bytes(store: ObjectStore, map_id: str, data: bytes, *, replace: bool = False, params: Params | None = None) -> int:
    """Write a snapshot's objects into ``map_id`` of ``store``; returns how many. The map must be empty
    (``replace``: it is deleted first); ``MapMismatch`` when it holds a header of other settings, or when
    the snapshot's differs from ``params`` (a service's: its store indexes under them)."""
    _document, header, objects = read_snapshot(data)
    if header.codec_version not in store.readable_codec_versions:
        raise MapMismatch(map_id, [("codec_version", header.codec_version, store.codec_version)])
    if params is not None:
        check_header(header, params, map_id=map_id)
    # The blobs were read by the versions they name; the store writes them anew in its own.
    header = dataclasses.replace(header, codec_version=store.codec_version)
    if replace:
        store.delete_map(map_id)
    elif store.count_objects(map_id):
        raise InvalidInput("map_id", "an empty map to restore into (or replace=true)", f"map {map_id!r} with objects")
    stored = store.open_map(map_id, header)
    theirs, ours = stored.to_record(), header.to_record()
    differences = [(name, theirs[name], ours[name]) for name in ours if name != "created_at_s" and theirs.get(name) != ours[name]]
    if differences:
        raise MapMismatch(map_id, differences)  # an empty map opened under other settings: restore with replace
    if objects:
        store.new_ids(map_id, max(o.id for o in objects))  # the id counter past every restored id
    for start in range(0, len(objects), RESTORE_BATCH):
        batch = [o.replace(version=1) for o in objects[start : start + RESTORE_BATCH]]
        store.commit(map_id, [], batch, [])
    return len(objects)


class ZipMapArchive:
    """``MapArchive``: the zip format of this module."""

    def snapshot(self, store: ObjectStore, map_id: str) -> bytes:
        return snapshot_bytes(store, map_id)

    def restore(
        self, store: ObjectStore, map_id: str, data: bytes, *, replace: bool = False, params: Params | None = None
    ) -> int:
        return restore_bytes(store, map_id, data, replace=replace, params=params)
