"""Each map's change log (``core.change``, the ``ChangeLog`` port), on every store: one entry per commit with
events, written by the commit itself (a refused commit appends nothing), numbered by the map's version with
no gap, trimmed to the store's bound, and read back with the objects' metadata."""

from __future__ import annotations

import time

import numpy as np
import pytest
from store_cases import MAP, make_object, moved

from arcloud.core.change import ChangesSince, MapChange
from arcloud.core.types import ObjectEvent, ObjectMeta
from arcloud.errors import StaleLease
from arcloud.stores import keys
from arcloud.stores.redis import RedisStore


def kinds(got: ChangesSince) -> list[list[tuple[str, int]]]:
    return [[(e.kind, e.object_id) for e in entry.events] for entry in got.entries]


def read(got: ChangesSince) -> tuple[tuple[object, ...], int, bool]:
    """What a read says but when its log began (``began``: the store's clock)."""
    return got.entries, got.version, got.complete


def test_each_commit_with_events_appends_one_entry_numbered_by_the_map_version(store) -> None:
    a, b = make_object(1, (0.0, 0, 0)), make_object(2, (2.0, 0, 0))
    assert store.changes_since(MAP, 0, 10) == ChangesSince((), 0, True)  # no entry yet: no began
    assert store.commit(MAP, [], MapChange.writing(MAP, [a, b]), frame_key="dev/f1")
    with store.lock(MAP, [1, 2], ttl_s=10, timeout_s=0) as lease:
        merged = ObjectEvent("merged", MAP, 2, merged_into=1, was_confirmed=True)
        change = MapChange(
            upserts=(moved(a, (0.5, 0, 0)),),
            deletes=(b,),
            events=(*MapChange.writing(MAP, [moved(a, (0.5, 0, 0))]).events, merged),
        )
        assert store.commit(MAP, [lease], change, frame_key="dev/f2")
    got = store.changes_since(MAP, 0, 10)
    assert got.complete and got.version == 2 and [e.version for e in got.entries] == [1, 2]
    assert [e.frame_key for e in got.entries] == ["dev/f1", "dev/f2"]
    assert kinds(got) == [[("created", 1), ("created", 2)], [("updated", 1), ("merged", 2)]]
    updated, gone = got.entries[1].events
    assert isinstance(updated.object, ObjectMeta) and updated.object.version == 2 and updated.map_id == MAP
    np.testing.assert_allclose(updated.object.bounds.min, moved(a, (0.5, 0, 0)).bounds.min)
    assert gone.object is None and gone.merged_into == 1 and gone.was_confirmed
    assert [e.version for e in store.changes_since(MAP, 1, 10).entries] == [2]
    assert read(store.changes_since(MAP, 2, 10)) == ((), 2, True)
    assert [e.version for e in store.changes_since(MAP, 0, 1).entries] == [1]  # at most limit


def test_a_refused_commit_appends_nothing(store) -> None:
    a = make_object(1, (0.0, 0, 0))
    assert store.commit(MAP, [], MapChange.writing(MAP, [a]), frame_key="dev/f1")
    with pytest.raises(StaleLease):  # written without its lock: the fence fails, nothing is written nor logged
        store.commit(MAP, [], MapChange.writing(MAP, [moved(a, (1.0, 0, 0))]), frame_key="dev/f2")
    assert not store.commit(MAP, [], MapChange.writing(MAP, [make_object(5, (4.0, 0, 0))]), frame_key="dev/f1")  # redelivered
    with store.lock(MAP, [1], ttl_s=10, timeout_s=0) as lease:
        assert store.commit(MAP, [lease], MapChange(misses={1: 1}), frame_key="dev/f3")  # counters only: no event
    got = store.changes_since(MAP, 0, 10)
    assert got.version == 1 and kinds(got) == [[("created", 1)]]
    assert [o.id for o in store.list_objects(MAP)] == [1]


def test_the_log_keeps_its_latest_entries_and_a_reader_behind_them_is_told(make_store) -> None:
    store = make_store(change_log_entries=5)
    for i in range(1, 301):
        assert store.commit(MAP, [], MapChange.writing(MAP, [make_object(i, (0.0, 0, 0.5 * i))]))
    every = store.changes_since(MAP, 0, 1000)
    kept = [e.version for e in every.entries]
    assert every.version == 300 and not every.complete and kept == list(range(kept[0], 301))
    # memory: exactly 5; Redis trims whole nodes of the stream (MAXLEN ~): at least 5, about a node more at most
    assert 5 <= len(kept) <= 5 + 200
    assert store.changes_since(MAP, kept[0] - 1, 1000).complete  # the reader saw up to the first kept
    assert not store.changes_since(MAP, kept[0] - 2, 1000).complete
    assert read(store.changes_since(MAP, 301, 10)) == ((), 300, False)  # ahead: not a version of this log


def test_deleting_a_map_empties_its_log_and_a_map_made_again_goes_on_from_its_version(store) -> None:
    """A reader that saw version 2 of the deleted map is told it missed changes, whatever the map made again wrote
    since (its versions restarting at 1 reached 2 and read as complete: a stream resumed on the old objects)."""
    for i in (1, 2):
        assert store.commit(MAP, [], MapChange.writing(MAP, [make_object(i, (i * 1.0, 0, 0))]))
    store.mark_published(MAP, 1)
    store.delete_map(MAP)
    assert read(store.changes_since(MAP, 2, 10)) == ((), 3, False)  # the deletion: one more version, no entry
    assert store.published_version(MAP) == 3  # nothing of the old map left to publish
    assert read(store.changes_since(MAP, 3, 10)) == ((), 3, True)
    for i in (1, 2):
        assert store.commit(MAP, [], MapChange.writing(MAP, [make_object(i, (i * 1.0, 0, 0))]))
    behind = store.changes_since(MAP, 2, 10)  # one that read up to 2 before the deletion: it re-reads the map
    assert (behind.version, behind.complete) == (5, False)
    assert [e.version for e in store.changes_since(MAP, 3, 10).entries] == [4, 5]  # one that read the empty map: complete
    assert store.changes_since(MAP, 3, 10).complete
    store.delete_map("never-made")  # a map no commit wrote has no version to move on
    assert store.changes_since("never-made", 0, 10) == ChangesSince((), 0, True)


def test_a_log_says_when_it_began_kept_through_a_deletion_and_another_store_s_log_another_time(make_store) -> None:
    """A review of a lost Redis: a reader that saw version 29 read a new map's 30 to 36 as following it. The time the
    log began (set with its first entry, kept with the version through a deletion) tells the two logs apart."""
    store = make_store()
    assert store.commit(MAP, [], MapChange.writing(MAP, [make_object(1, (0.0, 0, 0))]))
    began = store.changes_since(MAP, 0, 10).began
    seconds, micro = began.split(".")
    assert seconds.isdigit() and len(micro) == 6 and abs(int(seconds) - time.time()) < 600
    assert store.commit(MAP, [], MapChange.writing(MAP, [make_object(2, (2.0, 0, 0))]))
    store.delete_map(MAP)
    assert store.changes_since(MAP, 1, 10).began == began  # the same log, emptied: its versions go on
    time.sleep(0.002)
    other = make_store()  # the store that lost the map: a new log, from 1 again
    assert other.commit(MAP, [], MapChange.writing(MAP, [make_object(5, (0.0, 0, 0))]))
    assert other.changes_since(MAP, 0, 10).began not in ("", began)


def test_how_far_the_log_was_published_is_only_raised(store) -> None:
    assert store.published_version(MAP) == 0
    store.mark_published(MAP, 3)
    store.mark_published(MAP, 2)  # a slower publisher: ignored
    assert store.published_version(MAP) == 3 and store.published_version("other") == 0


def test_on_redis_the_log_is_a_stream_under_the_map_tag(redis_store: RedisStore) -> None:
    redis_store.commit(MAP, [], MapChange.writing(MAP, [make_object(1, (0.0, 0, 0))]), frame_key="dev/f1")
    [(entry_id, fields)] = redis_store.client.xrange(keys.changes_key(MAP))
    assert entry_id == b"1-0" and set(fields) == {b"at", b"frame", b"events"}
    assert redis_store.client.get(keys.version_key(MAP)) == b"1"
    assert keys.hash_tag(keys.changes_key(MAP)) == keys.hash_tag(keys.meta_key(MAP)) == MAP
