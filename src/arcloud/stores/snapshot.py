"""A map as one file, and back into any ``ObjectStore`` (embedded or Redis): ``arcloud maps snapshot |
restore | copy`` and the API's ``/v1/maps/{map}/snapshot``.

The file is a zip: ``snapshot.json`` (``format``, the map id it was taken of, its header, the codec
version, the object count) and, per object, ``objects/<id>.meta`` (``codec.encode_meta``) and
``objects/<id>.voxels`` (``codec.encode_voxels``), so a restore is exact: ids, labels, scores, boxes,
status, every voxel's weight, votes, sightings and colour. Only the versions (the stores' write fences) start
again at 1. A restore writes into an empty map (or replaces the map, when asked) under the snapshot's header
(its codec version must be the store's), keeps the ids and moves the map's id counter past them.

A restore writes in bounded commits, so that no request holds a shared store (Redis runs one script at a time):
at most ``RESTORE_BATCH`` objects, ``RESTORE_BATCH_CELLS`` index cells and ``RESTORE_BATCH_VOXELS`` voxels a
commit, each object covering at most ``cells.MAX_OBJECT_CELLS`` cells (the snapshot is refused otherwise, before
anything is written); a long restore logs how far it got every ``PROGRESS_LOG_S``.
"""

from __future__ import annotations

import io
import json
import logging
import re
import time
import zipfile
import zlib
from collections.abc import Callable, Iterator, Sequence

import numpy as np

from arcloud.core.change import MapChange
from arcloud.core.checks import check_finite_number, check_id, describe
from arcloud.core.header import MapHeader, check_header
from arcloud.core.types import AABB, MapObject, Params
from arcloud.core.voxels import keys_bounds
from arcloud.errors import InvalidInput, MapMismatch, StoreError, StoreUnavailable
from arcloud.ports import ObjectStore
from arcloud.stores import codec
from arcloud.stores.cells import MAX_OBJECT_CELLS, check_object_cells

log = logging.getLogger(__name__)

FORMAT = "arcloud.snapshot.v1"
RESTORE_BATCH = 16  # objects per commit, at most
RESTORE_BATCH_CELLS = MAX_OBJECT_CELLS  # index cells per commit, at most: about 10 ms of Redis a script
RESTORE_BATCH_VOXELS = 1 << 18  # voxels per commit, at most (an object of more goes alone): a few MB of blobs
PROGRESS_LOG_S = 5.0  # a long restore says how far it got this often
MAX_UNPACKED_BYTES = 2**30  # a snapshot whose members unpack to more is refused (zip bombs); a real map is a few MB
#: Nor may it unpack to more than this many times its own size (plus ``UNPACKED_SLACK_BYTES``): its blobs are
#: compressed already (a snapshot of a real map unpacks to about 1x), and a 1 MB file of zeros unpacked to 1 GB.
MAX_UNPACKED_OVER_PACKED = 8
UNPACKED_SLACK_BYTES = 2**20
#: The largest object id restored: what a JSON number carries exactly (the viewer reads ids as doubles).
MAX_OBJECT_ID = 2**53 - 1
#: The largest count (frames, votes) and time (Unix s: the last second of the year 9999) an object may hold: within
#: a float's range is not enough (a floor vote of 10**400 failed every frame of its map, an update time of 1e308
#: every read of its objects: a review).
MAX_COUNT = 2**53
MAX_TIME_S = 253_402_300_799
#: How far ``bounds`` may differ from its voxels' box: float rounding, never a voxel.
BOUNDS_TOLERANCE_M = 1e-6
#: How far a box (``aabb``, ``obb``) may reach past its voxels' box: the step completes boxes down to the floor
#: (``floor_reach_max_m``, 1 m) and under a table (a chair's width), never by metres; a box 1e300 m wide is not one
#: the step made.
BOX_REACH_M = 4.0
_META_MEMBER = re.compile(r"objects/(.*)\.meta")
# What reading a malformed file raises: zipfile's own errors, a corrupt deflate stream (zlib.error), a member
# name outside objects/ (IndexError), an encrypted or oddly compressed member (RuntimeError, NotImplementedError),
# a number past the largest float (OverflowError),
# JSON nested too deep (RecursionError), a blob the codec refuses (StoreError: here the file's fault, not a store's).
UNREADABLE = (
    zipfile.BadZipFile,
    zipfile.LargeZipFile,
    zlib.error,
    EOFError,
    KeyError,
    IndexError,
    ValueError,
    OverflowError,
    TypeError,
    RuntimeError,
    StoreError,
)


#: Reads of a map's objects a snapshot tries before giving up on one no commit landed in the middle of.
SNAPSHOT_READS = 5


def consistent_objects(store: ObjectStore, map_id: str) -> list[MapObject]:
    """Every object of the map as of one version: read again when a commit landed while they were read (a large map
    is read in batches, and a merge between two of them would put one object's voxels in the snapshot twice, or in
    none of it). ``StoreUnavailable`` when every one of ``SNAPSHOT_READS`` reads met a commit."""
    for _ in range(SNAPSHOT_READS):
        before = store.changes_since(map_id, 0, 0).version
        objects = store.list_objects(map_id)
        if store.changes_since(map_id, 0, 0).version == before:
            return objects
    raise StoreUnavailable(
        f"snapshot of map {map_id}: the map changed during each of {SNAPSHOT_READS} reads of its objects; try again "
        "when fewer frames of it are being processed"
    )


def snapshot_bytes(store: ObjectStore, map_id: str) -> bytes:
    """The map's header and objects as a snapshot file's bytes, all of one version (``consistent_objects``;
    ``InvalidInput`` for a map never opened)."""
    header = store.map_header(map_id)
    if header is None:
        raise InvalidInput("map_id", "a map with data", repr(map_id))
    objects = consistent_objects(store, map_id)
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
            most = min(MAX_UNPACKED_BYTES, MAX_UNPACKED_OVER_PACKED * len(data) + UNPACKED_SLACK_BYTES)
            if unpacked > most:
                raise InvalidInput(
                    "snapshot",
                    f"at most {most} bytes unpacked ({MAX_UNPACKED_OVER_PACKED} times its {len(data)} bytes + 1 MiB, at most "
                    f"{MAX_UNPACKED_BYTES})",
                    f"{unpacked} bytes",
                )
            document = json.loads(archive.read("snapshot.json"))
            if not isinstance(document, dict) or document.get("format") != FORMAT:
                raise InvalidInput(
                    "snapshot", f"a {FORMAT} file", f"format {document.get('format') if isinstance(document, dict) else None!r}"
                )
            header = MapHeader.from_record(document["header"])
            names: set[str] = set()
            for name in archive.namelist():  # zipfile reads the last of a name's members: the others go unchecked
                if name in names:
                    raise InvalidInput("snapshot", "each member once", f"member {describe(name)} more than once")
                names.add(name)
            ids = sorted(_object_id(name) for name in names if name.endswith(".meta"))
            objects = [
                codec.decode_object(i, archive.read(f"objects/{i}.meta"), archive.read(f"objects/{i}.voxels")) for i in ids
            ]
    except InvalidInput:
        raise  # what is wrong is named already
    except UNREADABLE as exc:
        raise InvalidInput("snapshot", f"a {FORMAT} zip file", f"one that cannot be read ({type(exc).__name__}: {exc})") from exc
    if len(objects) != document.get("objects"):
        raise InvalidInput("snapshot", f"{document.get('objects')} objects, as it says", f"{len(objects)}")
    for obj in objects:
        check_object(obj, header)
    return document, header, objects


def _object_id(member: str) -> int:
    """The id a metadata member's name gives (``objects/<id>.meta``); ``InvalidInput`` naming it otherwise."""
    found = _META_MEMBER.fullmatch(member)
    if found is None:
        raise InvalidInput("snapshot", "metadata members objects/<id>.meta", f"member {describe(member)}")
    text = found.group(1)
    if not (text.isascii() and text.isdigit() and len(text) <= 16 and text[0] != "0" and int(text) <= MAX_OBJECT_ID):
        raise InvalidInput(f"objects/{text[:40]}.id", f"an object id from 1 to {MAX_OBJECT_ID}", describe(text))
    return int(text)


def check_object(obj: MapObject, header: MapHeader) -> None:
    """``InvalidInput`` naming ``objects/<id>.<field>`` unless ``obj`` is what the step could have stored in a map
    of ``header`` (the module docstring lists the checks)."""
    where = f"objects/{obj.id}"
    if not 1 <= obj.id <= MAX_OBJECT_ID:
        raise InvalidInput(f"{where}.id", f"an object id from 1 to {MAX_OBJECT_ID}", obj.id)
    if obj.label not in header.classes:
        raise InvalidInput(f"{where}.label", f"one of the map's classes {', '.join(header.classes)}", describe(obj.label))
    for name in ("score", "label_purity"):
        value = check_finite_number(f"{where}.{name}", getattr(obj, name))
        if not 0.0 <= value <= 1.0:
            raise InvalidInput(f"{where}.{name}", "a number from 0 to 1", describe(value))
    for name, most in (
        ("score_sum", MAX_COUNT),
        ("n_frames", MAX_COUNT),
        ("created_at_s", MAX_TIME_S),
        ("updated_at_s", MAX_TIME_S),
    ):
        if not 0 <= check_finite_number(f"{where}.{name}", getattr(obj, name)) <= most:
            raise InvalidInput(f"{where}.{name}", f"a number from 0 to {most}", describe(getattr(obj, name)))
    for device in sorted(obj.devices):
        check_id(f"{where}.devices", device)
    if any(not (abs(height) <= MAX_COUNT and 0 <= count <= MAX_COUNT) for height, count in obj.floor_votes.items()):
        raise InvalidInput(f"{where}.floor_votes", f"height bins and counts from 0 to {MAX_COUNT}", describe(obj.floor_votes))
    if any(
        not (0 <= direction < 360 and 1 <= frames <= MAX_COUNT and abs(offset) <= MAX_COUNT)
        for direction, (frames, offset) in obj.wall_votes.items()
    ):
        raise InvalidInput(
            f"{where}.wall_votes", f"directions from 0 to 359 with frames from 1 to {MAX_COUNT}", describe(obj.wall_votes)
        )
    for name in ("apart", "spanned"):  # other object's id -> frames
        counts = getattr(obj, name)
        if any(
            not 1 <= other <= MAX_OBJECT_ID or other == obj.id or not 1 <= frames <= MAX_COUNT for other, frames in counts.items()
        ):
            raise InvalidInput(f"{where}.{name}", f"other objects' ids with frames from 1 to {MAX_COUNT}", describe(counts))
    if obj.keys.size == 0:
        raise InvalidInput(f"{where}.voxels", "at least one voxel", "none")
    for name in ("weights", "seen", "votes"):
        values = getattr(obj, name)
        if values is not None and not (np.all(np.isfinite(values)) and np.all(values >= 0)):
            raise InvalidInput(f"{where}.{name}", "finite numbers >= 0", "a negative or non-finite value")
    voxels_lo, voxels_hi = keys_bounds(obj.keys, header.voxel_size_m)
    bounds = _finite_box(f"{where}.bounds", obj.bounds)
    outside = np.any(bounds.min > voxels_lo + BOUNDS_TOLERANCE_M) or np.any(bounds.max < voxels_hi - BOUNDS_TOLERANCE_M)
    slack_m = header.voxel_size_m + BOUNDS_TOLERANCE_M
    if outside or np.any(bounds.min < voxels_lo - slack_m) or np.any(bounds.max > voxels_hi + slack_m):
        raise InvalidInput(
            f"{where}.bounds",
            f"the box of its voxels, {_corners(voxels_lo, voxels_hi)} (within a voxel)",
            _corners(bounds.min, bounds.max),
        )
    check_object_cells(f"{where}.bounds", bounds.min, bounds.max, header.index_cell_m)  # what one write may index
    aabb = _finite_box(f"{where}.aabb", obj.aabb)
    aabb_lo, aabb_hi, near_box = aabb.min, aabb.max, bounds
    if header.world2aligned is not None:  # the aabb is in the aligned frame: its corners back in the world
        world2aligned = np.asarray(header.world2aligned, np.float64)
        aabb_lo, aabb_hi = _moved_box(aabb_lo, aabb_hi, np.linalg.inv(world2aligned))
        near_box = AABB(*_moved_box(bounds.min, bounds.max, world2aligned))  # how far it reaches: in its own frame
    if not (_meets(aabb_lo, aabb_hi, bounds) and _near(aabb.min, aabb.max, near_box)):
        raise InvalidInput(
            f"{where}.aabb",
            f"a box meeting its voxels' {_corners(bounds.min, bounds.max)}, within {BOX_REACH_M} m of it",
            _corners(aabb.min, aabb.max),
        )
    obb = obj.obb
    if obb is None:
        raise InvalidInput(f"{where}.obb", "a box (an object with voxels has one)", "none")
    parts = (np.asarray(obb.center, np.float64), np.asarray(obb.size, np.float64), np.asarray(obb.rotation, np.float64))
    if not (all(np.all(np.isfinite(p)) for p in parts) and np.isfinite(obb.yaw_rad)) or np.any(parts[1] < 0):
        raise InvalidInput(
            f"{where}.obb", "a finite centre, rotation and yaw and sizes >= 0", "a non-finite value or a negative size"
        )
    reach = np.abs(parts[2]) @ parts[1] / 2  # half the extent of the oriented box along each world axis
    if not (_meets(parts[0] - reach, parts[0] + reach, bounds) and _near(parts[0] - reach, parts[0] + reach, bounds)):
        raise InvalidInput(
            f"{where}.obb",
            f"a box meeting its voxels' {_corners(bounds.min, bounds.max)}, within {BOX_REACH_M} m of it",
            f"centre {parts[0].round(3).tolist()}, size {parts[1].round(3).tolist()}",
        )


def _finite_box(field: str, box: AABB | None) -> AABB:
    """``box`` when it has finite corners, min <= max; else ``InvalidInput`` naming ``field``."""
    if box is None:
        raise InvalidInput(field, "a box (an object with voxels has one)", "none")
    lo, hi = np.asarray(box.min, np.float64), np.asarray(box.max, np.float64)
    if lo.shape != (3,) or hi.shape != (3,) or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))) or np.any(lo > hi):
        raise InvalidInput(field, "finite corners min <= max", _corners(lo, hi))
    return AABB(lo, hi)


def _meets(lo: np.ndarray, hi: np.ndarray, box: AABB) -> bool:
    """Whether [lo, hi] and ``box`` share a point (touching counts)."""
    return bool(np.all(lo <= box.max + BOUNDS_TOLERANCE_M) and np.all(box.min <= hi + BOUNDS_TOLERANCE_M))


def _moved_box(lo: np.ndarray, hi: np.ndarray, transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The axis-aligned box of the corners of [lo, hi] moved by a rigid (4, 4) ``transform``."""
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    moved = corners @ transform[:3, :3].T + transform[:3, 3]
    return moved.min(axis=0), moved.max(axis=0)


def _near(lo: np.ndarray, hi: np.ndarray, box: AABB) -> bool:
    """Whether [lo, hi] lies within ``BOX_REACH_M`` of ``box`` on every side."""
    return bool(np.all(lo >= box.min - BOX_REACH_M) and np.all(hi <= box.max + BOX_REACH_M))


def _corners(lo: np.ndarray, hi: np.ndarray) -> str:
    return f"min {np.round(np.asarray(lo, np.float64), 4).tolist()} max {np.round(np.asarray(hi, np.float64), 4).tolist()}"


def restore_bytes(
    store: ObjectStore,
    map_id: str,
    data: bytes,
    *,
    replace: bool = False,
    params: Params | None = None,
    forget: Callable[[], None] | None = None,
) -> int:
    """Write a snapshot's objects into ``map_id`` of ``store``; returns how many. The map must be empty
    (``replace``: it is deleted first, after ``forget()``, once the file is checked: the service drops the map's
    frame records and counts there, as a DELETE does); ``MapMismatch`` when it holds a header of other settings, or
    when the snapshot's differs from ``params`` (a service's: its store indexes under them)."""
    _document, header, objects = read_snapshot(data)
    if header.codec_version != store.codec_version:
        raise MapMismatch(map_id, [("codec_version", header.codec_version, store.codec_version)])
    if params is not None:
        check_header(header, params, map_id=map_id)
    if replace:
        if forget is not None:
            forget()
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
    started = last_log = time.monotonic()
    written = 0
    for batch in restore_batches(objects, header.index_cell_m):
        store.commit(map_id, [], MapChange.writing(map_id, [o.replace(version=1) for o in batch]))
        written += len(batch)
        if time.monotonic() - last_log >= PROGRESS_LOG_S:
            last_log = time.monotonic()
            log.info("map %s: restoring, %d of %d objects written in %.0f s", map_id, written, len(objects), last_log - started)
    return len(objects)


def restore_batches(objects: Sequence[MapObject], cell_m: float) -> Iterator[list[MapObject]]:
    """``objects`` in order, in batches of at most ``RESTORE_BATCH`` objects, ``RESTORE_BATCH_CELLS`` index cells of
    ``cell_m`` and ``RESTORE_BATCH_VOXELS`` voxels (an object over one of these alone in its batch)."""
    batch: list[MapObject] = []
    n_cells = n_voxels = 0
    for obj in objects:
        assert obj.bounds is not None  # checked: check_object
        cells = check_object_cells(f"objects/{obj.id}.bounds", obj.bounds.min, obj.bounds.max, cell_m)
        if batch and (
            len(batch) == RESTORE_BATCH
            or n_cells + cells > RESTORE_BATCH_CELLS
            or n_voxels + obj.keys.size > RESTORE_BATCH_VOXELS
        ):
            yield batch
            batch, n_cells, n_voxels = [], 0, 0
        batch.append(obj)
        n_cells += cells
        n_voxels += obj.keys.size
    if batch:
        yield batch


class ZipMapArchive:
    """``MapArchive``: the zip format of this module (its two functions)."""

    snapshot = staticmethod(snapshot_bytes)
    restore = staticmethod(restore_bytes)
