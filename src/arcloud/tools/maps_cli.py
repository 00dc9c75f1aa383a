"""``arcloud maps list | snapshot | restore | copy``: maps as things an operator keeps and moves.

    arcloud maps list --url http://127.0.0.1:8000 --token $ADMIN              # or --redis redis://...
    arcloud maps snapshot --map kitchen --out kitchen.zip --url http://127.0.0.1:8000 --token $ADMIN
    arcloud maps restore --map kitchen --in kitchen.zip --redis redis://127.0.0.1:6379/0 [--replace]
    arcloud maps copy --map kitchen --from http://127.0.0.1:8000 --to redis://10.0.0.5:6379/0 --token $ADMIN

A place is a running service (``http(s)://URL``, through its API with an admin key: the embedded store is
reachable only so) or a Redis (``redis://URL``, directly). Snapshots are ``arcloud.stores.snapshot`` files:
the header and every object exactly (ids kept; versions start again at 1).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

REDIS_SCHEMES = ("redis://", "rediss://", "unix://", "redis+cluster://", "rediss+cluster://")


class HttpPlace:
    """A running service, through its API."""

    def __init__(self, url: str, token: str | None) -> None:
        from arcloud.client.http import ArcloudClient

        self.client = ArcloudClient(url, token=token)

    def list_maps(self) -> list[dict[str, Any]]:
        return [{"map_id": m.map_id, "objects": m.objects, "updated_at": m.updated_at} for m in self.client.list_maps()]

    def snapshot(self, map_id: str) -> bytes:
        return self.client.snapshot(map_id)

    def restore(self, map_id: str, data: bytes, replace: bool) -> int:
        return self.client.restore(map_id, data, replace=replace).restored_objects

    def close(self) -> None:
        self.client.close()


class RedisPlace:
    """A Redis, directly (the store its index cells size from the map's header)."""

    def __init__(self, url: str) -> None:
        self.url = url

    def _store(self, cell_m: float | None = None) -> Any:
        from arcloud.core.types import Params
        from arcloud.stores.redis import RedisStore

        return RedisStore(self.url, cell_m=cell_m or Params().index_cell_m)

    def list_maps(self) -> list[dict[str, Any]]:
        store = self._store()
        try:
            updated = store.list_maps()
            return [{"map_id": m, "objects": store.count_objects(m), "updated_at": _iso(updated[m])} for m in sorted(updated)]
        finally:
            store.close()

    def snapshot(self, map_id: str) -> bytes:
        from arcloud.stores.snapshot import snapshot_bytes

        store = self._store()
        try:
            return snapshot_bytes(store, map_id)
        finally:
            store.close()

    def restore(self, map_id: str, data: bytes, replace: bool) -> int:
        from arcloud.stores.snapshot import read_snapshot, restore_bytes

        _, header, _ = read_snapshot(data)
        store = self._store(header.index_cell_m)  # the map's index cells, whatever this machine's defaults
        try:
            return restore_bytes(store, map_id, data, replace=replace)
        finally:
            store.close()

    def close(self) -> None:
        return None


def _iso(seconds: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(seconds)) if seconds else "-"


def open_place(where: str, token: str | None) -> HttpPlace | RedisPlace:
    from arcloud.errors import InvalidInput

    if where.startswith(REDIS_SCHEMES):
        return RedisPlace(where)
    if where.startswith(("http://", "https://")):
        return HttpPlace(where, token)
    raise InvalidInput(
        "place", "a service URL (http://, https://) or a Redis URL (redis://, rediss://, unix://, redis+cluster://)", repr(where)
    )


def add_maps_commands(subparsers: argparse._SubParsersAction) -> None:
    maps = subparsers.add_parser(
        "maps",
        help="list maps, snapshot one to a file, restore or copy it (service or Redis)",
        description="Places: a running service (--url, through its API; an admin key) or a Redis (--redis, directly).",
    )
    actions = maps.add_subparsers(dest="maps_command", required=True)

    def place_options(parser: argparse.ArgumentParser) -> None:
        where = parser.add_mutually_exclusive_group()
        where.add_argument("--url", help="a running service (default http://127.0.0.1:8000)")
        where.add_argument("--redis", metavar="URL", help="a Redis, directly")
        parser.add_argument("--token", default=None, help="API key token (default $ARCLOUD_TOKEN)")

    listing = actions.add_parser("list", help="the maps, with their objects and last change")
    place_options(listing)
    listing.set_defaults(handler=run_list)
    snapshot = actions.add_parser("snapshot", help="write one map to a file")
    place_options(snapshot)
    snapshot.add_argument("--map", dest="map_id", required=True)
    snapshot.add_argument("--out", type=Path, required=True, help="the snapshot file to write")
    snapshot.set_defaults(handler=run_snapshot)
    restore = actions.add_parser("restore", help="write a snapshot file into a map")
    place_options(restore)
    restore.add_argument("--map", dest="map_id", required=True)
    restore.add_argument("--in", dest="source", type=Path, required=True, help="the snapshot file")
    restore.add_argument("--replace", action="store_true", help="delete the map first (else it must be empty)")
    restore.set_defaults(handler=run_restore)
    copy = actions.add_parser("copy", help="copy a map from one place to another")
    copy.add_argument("--map", dest="map_id", required=True)
    copy.add_argument("--from", dest="source", required=True, help="a service URL or a Redis URL")
    copy.add_argument("--to", dest="target", required=True, help="a service URL or a Redis URL")
    copy.add_argument("--to-map", default=None, help="the map id there (default the same)")
    copy.add_argument("--token", default=None, help="API key token for both places (default $ARCLOUD_TOKEN)")
    copy.add_argument("--to-token", default=None, help="another token for --to")
    copy.add_argument("--replace", action="store_true", help="replace the map there (else it must be empty)")
    copy.set_defaults(handler=run_copy)


def _place(args: argparse.Namespace) -> HttpPlace | RedisPlace:
    return open_place(args.redis or args.url or "http://127.0.0.1:8000", args.token)


def run_list(args: argparse.Namespace) -> int:
    place = _place(args)
    try:
        maps = place.list_maps()
    finally:
        place.close()
    print(f"{'MAP':<32}  {'OBJECTS':>7}  UPDATED (UTC)")
    for row in maps:
        print(f"{row['map_id']:<32}  {row['objects']:>7}  {row['updated_at'] or '-'}")
    return 0


def run_snapshot(args: argparse.Namespace) -> int:
    place = _place(args)
    try:
        data = place.snapshot(args.map_id)
    finally:
        place.close()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_bytes(data)
    print(f"wrote {args.out} ({len(data)} bytes)", file=sys.stderr)
    return 0


def run_restore(args: argparse.Namespace) -> int:
    place = _place(args)
    try:
        restored = place.restore(args.map_id, args.source.read_bytes(), args.replace)
    finally:
        place.close()
    print(f"restored {restored} objects into map {args.map_id}", file=sys.stderr)
    return 0


def run_copy(args: argparse.Namespace) -> int:
    source = open_place(args.source, args.token)
    target = open_place(args.target, args.to_token or args.token)
    try:
        copied = target.restore(args.to_map or args.map_id, source.snapshot(args.map_id), args.replace)
    finally:
        source.close()
        target.close()
    print(f"copied map {args.map_id} ({copied} objects) to map {args.to_map or args.map_id} at {args.target}", file=sys.stderr)
    return 0
