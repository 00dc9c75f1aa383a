"""Map snapshot files (``arcloud.stores.snapshot``) with one object edited, as a hostile or broken client would
send them: its metadata re-encoded with fields changed, or its members renamed to another id. Imported as
``from snapshot_edits import ...`` (``tests/`` is on sys.path)."""

from __future__ import annotations

import io
import zipfile
from collections.abc import Callable

from arcloud.core.types import MapObject
from arcloud.stores import codec


def _rezipped(data: bytes, edit: Callable[[str, bytes], tuple[str, bytes]]) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(data)) as source, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as target:
        for name in source.namelist():
            target.writestr(*edit(name, source.read(name)))
    return out.getvalue()


def first_object_id(data: bytes) -> int:
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        return min(int(n.split("/")[1].removesuffix(".meta")) for n in archive.namelist() if n.endswith(".meta"))


def with_object_changed(data: bytes, object_id: int, **changes: object) -> bytes:
    """The snapshot with object ``object_id``'s metadata written again with ``changes`` (``MapObject`` fields)."""
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        obj: MapObject = codec.decode_object(
            object_id, archive.read(f"objects/{object_id}.meta"), archive.read(f"objects/{object_id}.voxels")
        )
    meta = codec.encode_meta(obj.replace(**changes))
    return _rezipped(data, lambda name, blob: (name, meta if name == f"objects/{object_id}.meta" else blob))


def with_object_renamed(data: bytes, object_id: int, new_name: str) -> bytes:
    """The snapshot with object ``object_id``'s members named ``objects/<new_name>.meta`` and ``.voxels``."""

    def rename(name: str, blob: bytes) -> tuple[str, bytes]:
        for suffix in (".meta", ".voxels"):
            if name == f"objects/{object_id}{suffix}":
                return f"objects/{new_name}{suffix}", blob
        return name, blob

    return _rezipped(data, rename)
