"""Hypothesis strategies for map snapshot files: a valid snapshot (``arcloud.stores.snapshot``) with its bytes
mutated, or rebuilt with one member mutated, renamed or its JSON given odd values."""

from __future__ import annotations

import io
import json
import zipfile

from frame_strategies import json_values, mutated_bytes
from hypothesis import strategies as st

ODD_MEMBER_NAMES = ["a.meta", "objects/x.meta", "objects/-1.meta", "objects/99999999999999999999.meta", "objects/1.meta/x.meta"]


@st.composite
def rebuilt_snapshots(draw: st.DrawFn, valid: bytes) -> bytes:
    """``valid`` rezipped (stored or deflated) with one member changed: its bytes mutated, or a value of
    ``snapshot.json`` (its header's too) replaced, and sometimes the member renamed."""
    source = zipfile.ZipFile(io.BytesIO(valid))
    names = source.namelist()
    target = draw(st.sampled_from(names))
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", draw(st.sampled_from([zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED]))) as rebuilt:
        for name in names:
            data = source.read(name)
            if name == target:
                if name == "snapshot.json" and draw(st.booleans()):
                    document = json.loads(data)
                    key = draw(st.sampled_from([*document, "header.voxel_size_m", "header.extra"]))
                    if key.startswith("header.") and isinstance(document.get("header"), dict):
                        document["header"][key.removeprefix("header.")] = draw(json_values)
                    else:
                        document[key] = draw(json_values)
                    data = json.dumps(document).encode()
                else:
                    data = draw(mutated_bytes(data))
                if draw(st.integers(0, 4)) == 0:
                    name = draw(st.sampled_from(ODD_MEMBER_NAMES))
            rebuilt.writestr(name, data)
    return out.getvalue()


def mutated_snapshots(valid: bytes) -> st.SearchStrategy[bytes]:
    return st.one_of(mutated_bytes(valid), rebuilt_snapshots(valid))
