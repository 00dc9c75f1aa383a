"""The map header at the service's edges (``arcloud.core.header``): a worker opens the map it is about
to write, so the first writer stores the settings the map's data means something under; the API checks
the header of a map a request reads or writes. Both refuse a map written under other settings with
``MapMismatch`` (the API answers 409), so that processes started with different ``Params`` never
write or read one map two ways; the API refuses a map whose deletion goes on with ``MapBeingDeleted`` (409)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from collections.abc import Mapping

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


def worker_settings(params: Params, codec_version: int) -> dict[str, object]:
    """What a worker maps with, as its heartbeat gives it: the settings a map's header holds (``map``: a worker with
    others fails every frame of the maps the others made) and a digest of all its ``Params`` (``params``: workers with
    others write two ways of mapping into the maps they share)."""
    record = MapHeader.from_params(params, codec_version, 0.0).to_record()
    del record["created_at_s"]
    everything = json.dumps(dataclasses.asdict(params), sort_keys=True, default=str)
    return {"map": record, "params": hashlib.sha256(everything.encode()).hexdigest()[:16]}


def settings_differences(theirs: Mapping[str, object], ours: Mapping[str, object]) -> list[str]:
    """``name: theirs X, ours Y`` for each map setting in which two ``worker_settings`` differ."""
    their_map, our_map = theirs.get("map"), ours.get("map")
    if not isinstance(their_map, Mapping) or not isinstance(our_map, Mapping):
        return []
    names = sorted(set(their_map) | set(our_map))
    return [f"{n}: theirs {their_map.get(n)}, ours {our_map.get(n)}" for n in names if their_map.get(n) != our_map.get(n)]


__all__ = ["check_map_header", "check_not_being_deleted", "open_map_checked", "settings_differences", "worker_settings"]
