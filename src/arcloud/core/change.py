"""What one commit changes in a map, and how a map's change log gives it back.

``MapChange`` is the one value the step hands the store (``MapStore.commit``): the objects it writes and
removes, the counters it moves, and the events that say so to listeners, in one vocabulary (``EventKind``:
created, updated, merged, deleted, retired). The store writes it and appends its events to the map's
change log in the same atomic step, so that whoever announces changes (server-sent events, Zenoh) reads
them from the log, never from a worker that may die between its write and its announcement.

A map's log is numbered by the map's *version*: every commit with events adds one, so the entries of a
map are 1, 2, 3, ... with no gap, and a reader that knows the last version it saw knows whether it missed
any (``ChangesSince.complete``). A log keeps its latest entries only (a store's bound); a reader too far
behind re-reads the map.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from arcloud.core.types import MapObject, ObjectEvent


@dataclass(frozen=True, slots=True)
class MapChange:
    """One frame's (or one writer's) change to a map, written at once (``MapStore.commit``).

    - ``upserts``: objects written, each at its stored version + 1 (1: new);
    - ``deletes``: objects removed, as read (at their stored version): merged into another, or deleted;
    - ``retired``: objects seen gone, as read: removed, and kept in the map's history;
    - ``misses`` / ``gone``: object id -> its new ``n_missed`` / ``n_gone``, for held objects not rewritten
      (counters: no new version, no event);
    - ``events``: what listeners are told, one per object written or removed; a change without events
      adds nothing to the map's change log."""

    upserts: tuple[MapObject, ...] = ()
    deletes: tuple[MapObject, ...] = ()
    retired: tuple[MapObject, ...] = ()
    misses: Mapping[int, int] = field(default_factory=dict)
    gone: Mapping[int, int] = field(default_factory=dict)
    events: tuple[ObjectEvent, ...] = ()

    @classmethod
    def writing(cls, map_id: str, upserts: Sequence[MapObject] = (), deletes: Sequence[MapObject] = ()) -> MapChange:
        """The change that writes ``upserts`` and deletes ``deletes``, for a writer with no state read to tell
        it more (a map restored from a file, a test): each upsert is ``created`` at version 1, else ``updated``,
        each delete ``deleted``; ``was_confirmed`` is the object's own status (a delete's as read)."""
        events = [
            ObjectEvent("created" if o.version == 1 else "updated", map_id, o.id, o, was_confirmed=o.version > 1 and o.confirmed)
            for o in upserts
        ]
        events += [ObjectEvent("deleted", map_id, o.id, was_confirmed=o.confirmed) for o in deletes]
        return cls(upserts=tuple(upserts), deletes=tuple(deletes), events=tuple(events))


@dataclass(frozen=True, slots=True)
class LoggedChange:
    """One entry of a map's change log: the events of one commit, the map's ``version`` after it (the entry's
    id) and the frame it recorded ("" for none). Each event's ``object`` is the object's ``ObjectMeta`` (a log
    keeps no voxels)."""

    version: int
    frame_key: str
    events: tuple[ObjectEvent, ...]


@dataclass(frozen=True, slots=True)
class ChangesSince:
    """What a change log holds after a version a reader saw (``ChangeLog.changes_since``): ``entries``, oldest
    first; ``version``, the map's version now (the last entry's, 0 before any); ``complete``: False when
    entries the reader has not seen are gone (trimmed, or the map was deleted since: a deletion moves the version
    on and empties the log, ``ObjectStore.delete_map``; or ``after`` is ahead of the map: not a version of this
    log), so that the reader must re-read the map instead."""

    entries: tuple[LoggedChange, ...]
    version: int
    complete: bool
    began: str = ""  # when the log began, by the store's clock ("" before its first entry): a reader that saw another
    #: ``began`` saw another log (the store lost the map and a new one began: its versions count again from 1)


def changes_after(entries: Sequence[LoggedChange], version: int, after: int, limit: int, began: str = "") -> ChangesSince:
    """``ChangesSince`` of a log holding ``entries`` (consecutive versions, oldest first) whose map is at
    ``version``, for a reader that saw up to ``after``: at most ``limit`` entries; ``began``: the log's."""
    if after > version:  # not a version of this log (another store's, or one that lost its data)
        return ChangesSince((), version, False, began)
    first = entries[0].version if entries else version + 1
    kept = [e for e in entries if e.version > after][: max(0, limit)]
    return ChangesSince(tuple(kept), version, after + 1 >= first or after == version, began)


__all__ = ["ChangesSince", "LoggedChange", "MapChange", "changes_after"]
