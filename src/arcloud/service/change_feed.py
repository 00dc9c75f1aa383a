"""The maps' change logs, published over Zenoh (or any ``UpdatePublisher``).

A commit appends its events to its map's change log in the same atomic write (``core.change``); this feed
reads each log from the version last published (``ChangeLog.published_version``, kept in the store, so
shared by every process) and publishes what follows, then records how far it went. Two callers:

- a worker, right after its commit (``publish_pending`` of its frame's map): events leave as soon as they
  did when the step published them itself;
- the API process, every ``sweep_s`` over every map (``run``): a worker that died between its commit and its
  publishing leaves entries behind, and the next sweep (or the map's next commit) publishes them.

Delivery is at least once: two processes may publish one entry (both read the cursor before either raised it);
a subscriber sees a state again, never a state skipped. An entry trimmed from the log before anyone published
it is lost to Zenoh (logged): the log keeps ``change_log_entries`` per map, far more than a sweep's worth.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable

from arcloud.errors import ArcloudError
from arcloud.ports import ChangeLog, UpdatePublisher

log = logging.getLogger(__name__)

ENTRIES_PER_READ = 256  # log entries read a call


class ChangeFeed:
    """Publishes the change logs of ``changes`` through ``publisher``. Thread-safe: one map at a time is
    published in this process (``publish_pending`` holds a lock), so its events leave in the log's order."""

    def __init__(self, changes: ChangeLog, publisher: UpdatePublisher) -> None:
        self.changes = changes
        self.publisher = publisher
        self._publishing = threading.Lock()

    def publish_pending(self, map_id: str) -> int:
        """Publish the map's entries after the version last published; returns how many events went out."""
        sent = 0
        with self._publishing:
            after = self.changes.published_version(map_id)
            while True:
                got = self.changes.changes_since(map_id, after, ENTRIES_PER_READ)
                if not got.complete and got.version > after:
                    first = got.entries[0].version if got.entries else got.version + 1
                    log.warning(
                        "map %s: change log entries %d to %d trimmed before they were published", map_id, after + 1, first - 1
                    )
                if not got.entries:
                    return sent
                events = [event for entry in got.entries for event in entry.events]
                self.publisher.publish(events)
                sent += len(events)
                after = got.entries[-1].version
                self.changes.mark_published(map_id, after)
                if len(got.entries) < ENTRIES_PER_READ:
                    return sent

    def sweep(self, map_ids: Iterable[str]) -> int:
        """``publish_pending`` of each map; a map whose log cannot be read is logged and skipped."""
        sent = 0
        for map_id in map_ids:
            try:
                sent += self.publish_pending(map_id)
            except ArcloudError as exc:
                log.warning("map %s: publishing its change log failed: %s", map_id, exc)
        return sent

    def run(self, stop: threading.Event, list_maps: Callable[[], Iterable[str]], sweep_s: float) -> None:
        """``sweep`` the maps ``list_maps`` gives every ``sweep_s`` until ``stop`` is set."""
        while not stop.wait(sweep_s):
            try:
                self.sweep(list_maps())
            except ArcloudError as exc:  # the store is down: try again at the next sweep
                log.warning("change feed: listing the maps failed: %s", exc)
            except Exception:
                log.exception("change feed: a sweep failed")


__all__ = ["ENTRIES_PER_READ", "ChangeFeed"]
