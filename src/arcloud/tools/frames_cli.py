"""Operators' commands on the frame queue (``arcloud.cli`` adds them with ``add_frames_commands``):

    arcloud frames failed --map kitchen [--limit 50]      # the map's failed frames: reason, deliveries, when
    arcloud frames retry --map kitchen --all              # queue every failed frame again
    arcloud frames retry --map kitchen phone-1/000123 phone-1/000124

They work on the Redis queue (``--redis URL``, default ``$ARCLOUD_STORE``); the embedded queue lives inside
``arcloud serve``. A retry queues the frame from its dead letter as a device posting it again would: the
queue's limits (``ARCLOUD_MAX_QUEUED_*``, read here as the service reads them) apply. Exit status: 0 done,
1 some frames refused by the queue's limits (listed with why), 2 bad input (unknown map, a frame that is
not failed or whose dead letter was dropped: nothing queued then).
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from arcloud.argtypes import positive_int

if TYPE_CHECKING:
    from arcloud.ports import FailedFrame
    from arcloud.stores.redis_queue import RedisFrameQueue

DEFAULT_LIMIT = 50
EVERY_FRAME = 2**31  # failed_frames' limit for --all


def add_frames_commands(subparsers: argparse._SubParsersAction) -> None:
    frames = subparsers.add_parser(
        "frames",
        help="list a map's failed frames, queue them again (Redis)",
        description="The frame queue's failed frames: why they failed, and queueing them again from their dead letters.",
    )
    commands = frames.add_subparsers(dest="frames_command", required=True)

    failed = commands.add_parser(
        "failed",
        help="a map's failed frames, latest first: reason, deliveries, when, whether it can be retried",
        description="The failed frames whose records are kept (ARCLOUD_FRAME_RECORD_RETENTION_S), latest first.",
    )
    _common_options(failed)
    failed.add_argument("--limit", type=positive_int, default=DEFAULT_LIMIT, help=f"at most this many (default {DEFAULT_LIMIT})")
    failed.set_defaults(handler=run_failed)

    retry = commands.add_parser(
        "retry",
        help="queue failed frames again from their dead letters",
        description="Queues each frame as a device posting it again would (the queue's limits apply). Exit 0 when all "
        "were queued, 1 when the queue refused some (each listed with why), 2 for bad input (nothing queued).",
    )
    _common_options(retry)
    retry.add_argument("--all", action="store_true", help="every failed frame of the map")
    retry.add_argument("frames", nargs="*", metavar="DEVICE/FRAME", help="the frames to queue again")
    retry.set_defaults(handler=run_retry)


def _common_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--map", dest="map_id", required=True, help="the map")
    parser.add_argument("--redis", metavar="URL", help="Redis URL (default: $ARCLOUD_STORE)")


def open_queue(args: argparse.Namespace) -> RedisFrameQueue:
    """The service's frame queue on Redis, with the service's limits and group (``ARCLOUD_*``), and the
    map checked to be known; ``ArcloudError`` otherwise."""
    from pydantic import ValidationError

    from arcloud.core.checks import check_map_id
    from arcloud.errors import ArcloudError, InvalidInput
    from arcloud.service.settings import Settings
    from arcloud.stores.redis_queue import RedisFrameQueue
    from arcloud.tools.service_cli import validation_problems

    check_map_id("--map", args.map_id)
    try:
        settings = Settings(**({"store": args.redis} if args.redis else {}))
    except ValidationError as exc:
        raise ArcloudError(f"invalid settings (options or ARCLOUD_* variables): {'; '.join(validation_problems(exc))}") from None
    if settings.embedded:
        raise ArcloudError("--redis: expected a Redis URL (or ARCLOUD_STORE); the embedded queue lives inside `arcloud serve`")
    queue = RedisFrameQueue(
        settings.store, group=settings.consumer_group, limits=settings.queue_limits(), shards=settings.ingest_shards
    )
    try:
        queue.check_shards()  # the map's records are in its shard of the service's number
    except InvalidInput as exc:
        queue.close()
        raise ArcloudError(f"{exc} (set ARCLOUD_INGEST_SHARDS as the service has it)") from None
    if not queue.known_map(args.map_id):
        queue.close()
        raise ArcloudError(f"--map: no frame of map {args.map_id!r} was accepted (unknown map)")
    return queue


def run_failed(args: argparse.Namespace) -> int:
    from datetime import UTC, datetime

    queue = open_queue(args)
    try:
        failed = queue.failed_frames(args.map_id, args.limit)
    finally:
        queue.close()
    if not failed:
        print(f"map {args.map_id}: no failed frames")
        return 0
    more = " (the latest; --limit for more)" if len(failed) == args.limit else ""
    print(f"map {args.map_id}: {len(failed)} failed frames{more}")
    width = max(len("FRAME"), *(len(f.frame_key) for f in failed))
    print(f"{'FRAME':<{width}}  DELIVERIES  FAILED AT (UTC)      RETRY  REASON")
    for f in failed:
        when = datetime.fromtimestamp(f.failed_at_s, UTC).strftime("%Y-%m-%d %H:%M:%S")
        retry = "yes" if f.retriable else "no"  # no: its dead letter was dropped (max_dead_letters)
        print(f"{f.frame_key:<{width}}  {f.deliveries:>10}  {when}  {retry:<5}  {f.reason}")
    return 0


def run_retry(args: argparse.Namespace) -> int:
    from arcloud.errors import ArcloudError, InvalidInput
    from arcloud.ports import QueueFull

    if args.all == bool(args.frames):
        raise ArcloudError("frames retry: expected --all or DEVICE/FRAME ..., not both or neither")
    queue = open_queue(args)
    try:
        failed = {f.frame_key: f for f in queue.failed_frames(args.map_id, EVERY_FRAME)}
        frame_keys = sorted(failed) if args.all else [_checked_frame_key(queue, args.map_id, key, failed) for key in args.frames]
        queued = refused = 0
        for key in frame_keys:
            try:
                if queue.retry_failed(args.map_id, key):
                    print(f"queued {key}")
                    queued += 1
                else:
                    print(f"not queued {key}: posted again since (queued, in progress or processed)")
            except (QueueFull, InvalidInput) as exc:  # the queue's limits; with --all, a dead letter dropped
                print(f"refused {key}: {exc}")
                refused += 1
    finally:
        queue.close()
    print(f"map {args.map_id}: {queued} queued, {refused} refused")
    return 1 if refused else 0


def _checked_frame_key(queue: RedisFrameQueue, map_id: str, key: str, failed: dict[str, FailedFrame]) -> str:
    """``key`` when it names a failed frame of the map whose dead letter is kept; ``InvalidInput`` otherwise."""
    from arcloud.core.checks import check_id
    from arcloud.errors import InvalidInput
    from arcloud.ports import not_retriable

    device_id, slash, frame_id = key.partition("/")
    if not slash:
        raise InvalidInput("DEVICE/FRAME", "a device id and a frame id joined by '/'", repr(key))
    check_id("device id", device_id)
    check_id("frame id", frame_id)
    found = failed.get(key)
    if found is None or not found.retriable:
        status = queue.frame_status(map_id, key)
        raise not_retriable(map_id, key, None if status is None else status.status)
    return key
