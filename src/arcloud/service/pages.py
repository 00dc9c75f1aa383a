"""A page of a map's objects (``GET /v1/maps/{map}/objects?limit=&cursor=``) reads what it returns, not the map.

Before, every page read and decoded the metadata of every object of the map (on a 1,500-object map about 100 ms a
page, whatever ``limit``). Now a page reads the map's object ids (``MapReader.object_ids``: on Redis the bounds
HASH's field names, a few bytes an object), or those a ``bbox`` finds through the spatial index, takes those after
the cursor in id order, and reads the metadata of ``limit + 1`` of them, then, while filters leave the page short,
about as many more as the share they kept says will fill it (at most ``MAX_READ_BATCH`` a read): with filters that
keep most objects, one read of ``limit + 1`` objects. Without ``limit``, the whole map, ``READ_BATCH`` at a time.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable, Sequence

from arcloud.errors import InvalidInput
from arcloud.ports import MapReader, ObjectMeta

READ_BATCH = 256  # object metadata read at a time without a limit
MAX_READ_BATCH = 4096
MAX_CURSOR_DIGITS = 19


def parse_cursor(cursor: str | None) -> int:
    """The id after which a page starts (0: the first page); ``InvalidInput`` naming ``cursor``."""
    if cursor is None:
        return 0
    if not cursor.isascii() or not cursor.isdigit() or len(cursor) > MAX_CURSOR_DIGITS:
        raise InvalidInput("cursor", "the next_cursor of a page before (an object id)", repr(cursor[:40]))
    return int(cursor)


def object_page(
    store: MapReader,
    map_id: str,
    ids: Sequence[int],
    keep: Callable[[ObjectMeta], bool],
    *,
    after: int = 0,
    limit: int | None = None,
) -> tuple[list[ObjectMeta], int | None]:
    """(the objects of ``ids`` (sorted) after id ``after`` that ``keep`` keeps, at most ``limit`` of them, in id
    order; the id the next page starts after, None on the last page), reading only the metadata it needs."""
    start = at = bisect.bisect_right(ids, after)
    batch = READ_BATCH if limit is None else limit + 1
    page: list[ObjectMeta] = []
    while at < len(ids):
        page += [o for o in store.object_meta(map_id, ids[at : at + batch]) if keep(o)]
        at += batch
        if limit is None:
            continue
        if len(page) > limit:
            return page[:limit], page[limit - 1].id
        # filters left the page short: read about what the share they kept so far says fills it
        need = limit + 1 - len(page)
        kept = (len(page) + 1) / (at - start + 2)  # (Laplace's rule: a first read that kept none says little)
        batch = min(MAX_READ_BATCH, max(need, math.ceil(need / kept)))
    return page, None


__all__ = ["MAX_READ_BATCH", "READ_BATCH", "object_page", "parse_cursor"]
