"""The map header at the service's edges (``arcloud.core.header``): a worker opens the map it is about
to write, so the first writer stores the settings the map's data means something under; the API checks
the header of a map a request reads or writes. Both refuse a map written under other settings with
``MapMismatch`` (the API answers 409), so that processes started with different ``Params`` never
write or read one map two ways; the API refuses a map whose deletion goes on with ``MapBeingDeleted`` (409)."""

from __future__ import annotations

import time

from arcloud.core.header import MapHeader, check_header
from arcloud.core.types import Params
from arcloud.ports import MapBeingDeleted, MapCatalog


def open_map_checked(store: MapCatalog, map_id: str, params: Params) -> None:
    """Store our header if the map has none; ``MapMismatch`` if its header says other settings."""
    ours = MapHeader.from_params(params, store.codec_version, time.time())
    check_store_header(store, store.open_map(map_id, ours), params, map_id)


def check_map_header(store: MapCatalog, map_id: str, params: Params, *, open_new: bool = False) -> None:
    """``MapMismatch`` if the map's stored header says other settings than ours; none stored: fine, and
    with ``open_new`` ours is stored (the map's first frame: one read a call otherwise, as a check)."""
    header = store.map_header(map_id)
    if header is not None:
        check_store_header(store, header, params, map_id)
        return
    check_not_being_deleted(store, map_id)
    if open_new:
        open_map_checked(store, map_id, params)


def check_not_being_deleted(store: MapCatalog, map_id: str) -> None:
    """``MapBeingDeleted`` while the map's deletion goes on. Asked of maps without a header only: a deletion
    takes the header away first, so a map that has one is not being deleted (no extra read on the common path)."""
    deletion = store.map_deletion(map_id)
    if deletion is not None and not deletion.done:
        raise MapBeingDeleted(deletion)


def check_store_header(store: MapCatalog, header: MapHeader, params: Params, map_id: str) -> None:
    """``check_header`` against ``params`` and the blob format ``store`` writes and reads."""
    check_header(header, params, codec_version=store.codec_version, map_id=map_id)


__all__ = ["check_map_header", "check_not_being_deleted", "open_map_checked"]
