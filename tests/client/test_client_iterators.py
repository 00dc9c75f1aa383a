"""The SDK's iterators against a real uvicorn server: the objects of a map a page at a time (each page asked for when
needed, every object once), and the event stream, which goes on through a restart of the service."""

from __future__ import annotations

import asyncio
import queue
import threading
from collections.abc import Iterator

import httpx
import pytest
from svc_helpers import BlobDetector, UvicornThread, cube, free_port, make_test_frame

from arcloud.client import ArcloudClient, AsyncArcloudClient
from arcloud.client.http import ServiceError
from arcloud.client.results import MapEvent, ObjectOut, ResetEvent, SnapshotEvent, UpsertEvent
from arcloud.core.change import MapChange
from arcloud.core.header import MapHeader
from arcloud.core.types import Params
from arcloud.service.event_stream import close_event_streams
from arcloud.service.settings import Settings
from arcloud.stores.memory import MemoryStore
from arcloud.tools.wiring import create_app

MAP = "paged"
N_OBJECTS = 23  # every third tentative (``cube``)
SETTINGS = Settings(detector="sim:0", workers=1, key_rate_per_s=0, event_poll_s=0.05)


@pytest.fixture(scope="module")
def paged_url() -> Iterator[str]:
    store = MemoryStore()
    store.open_map(MAP, MapHeader.from_params(Params(), codec_version=store.codec_version, created_at_s=1.0))
    store.commit(MAP, [], MapChange.writing(MAP, [cube(i) for i in range(1, N_OBJECTS + 1)]))
    with UvicornThread(create_app(SETTINGS, store=store, detector=BlobDetector())) as server:
        yield server.url


def test_iter_objects_yields_every_object_once_asking_for_each_page_when_needed(paged_url: str) -> None:
    pages: list[httpx.URL] = []
    http = httpx.Client(base_url=paged_url, event_hooks={"request": [lambda request: pages.append(request.url)]})
    with http, ArcloudClient(paged_url, http=http) as client:
        objects = client.iter_objects(MAP, include_tentative=True, page_size=5)
        first = next(objects)
        assert isinstance(first, ObjectOut) and first.id == 1 and len(pages) == 1  # one page asked for, not five
        rest = list(objects)
        assert [o.id for o in [first, *rest]] == list(range(1, N_OBJECTS + 1))
        assert len(pages) == 5 and all(url.params["limit"] == "5" for url in pages)
        confirmed = [o.id for o in client.iter_objects(MAP, page_size=4)]
        assert confirmed == [i for i in range(1, N_OBJECTS + 1) if i % 3] and len(confirmed) == len(set(confirmed))
        assert [o.id for o in client.iter_objects(MAP, label="tv", page_size=3, include_tentative=True)] == list(
            range(1, N_OBJECTS + 1, 2)
        )


def test_async_iter_objects_and_maps(paged_url: str) -> None:
    async def run() -> tuple[list[int], list[str]]:
        async with AsyncArcloudClient(paged_url) as client:
            ids = [o.id async for o in client.iter_objects(MAP, include_tentative=True, page_size=7)]
            maps = [m.map_id async for m in client.iter_maps(page_size=1)]
            return ids, maps

    ids, maps = asyncio.run(run())
    assert ids == list(range(1, N_OBJECTS + 1)) and maps == [MAP]


class Follower:
    """``client.events`` followed in a thread, each event (or the error that ended it) put in ``received``; stops
    after the event that comes once ``stop`` is set."""

    def __init__(self, client: ArcloudClient, map_id: str, *, wait_for_map: bool = False) -> None:
        self.received: queue.Queue[MapEvent | Exception] = queue.Queue()
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, args=(client, map_id, wait_for_map), daemon=True)
        self.thread.start()

    def _run(self, client: ArcloudClient, map_id: str, wait_for_map: bool) -> None:
        try:
            for event in client.events(map_id, include_tentative=True, wait_for_map=wait_for_map):
                self.received.put(event)
                if self.stop.is_set():
                    return
        except Exception as exc:  # noqa: BLE001 - handed to the test, which fails with it
            self.received.put(exc)

    def next_of(self, *kinds: type, timeout_s: float = 20.0) -> MapEvent:
        """The next event of one of ``kinds`` (skipping others, e.g. ``DeviceEvent``)."""
        while True:
            event = self.received.get(timeout=timeout_s)
            if isinstance(event, Exception):
                raise event
            if isinstance(event, kinds):
                return event


def test_events_yield_a_frame_processed_after_they_started_and_resume_after_a_restart_missing_nothing() -> None:
    """The service restarts; meanwhile a worker elsewhere commits (as on Redis, the map outlives the service): the
    client connects again with ``Last-Event-ID`` and gets that change, no snapshot."""
    store = MemoryStore()
    port = free_port()
    first_app = create_app(SETTINGS, store=store, detector=BlobDetector())
    with ArcloudClient(f"http://127.0.0.1:{port}", max_retries=10, backoff_s=0.05) as client:
        with UvicornThread(first_app, port=port):
            client.send_frame(make_test_frame(0, map_id="live", level=True))
            client.wait_until_processed("live", timeout_s=20)  # the map exists: its stream can open
            follower = Follower(client, "live")
            snapshot = follower.next_of(SnapshotEvent)
            assert isinstance(snapshot, SnapshotEvent) and [o.version for o in snapshot.objects] == [1]
            assert snapshot.version == 1  # the map's change log: one entry
            (obj,) = snapshot.objects
            client.send_frame(make_test_frame(1, map_id="live", level=True))
            upsert = follower.next_of(UpsertEvent)
            assert isinstance(upsert, UpsertEvent) and upsert.object.id == obj.id and upsert.object.version == 2
            close_event_streams(first_app)  # as `arcloud serve` does on shutdown: the service ends the stream
        with store.lock("live", [obj.id], ttl_s=5, timeout_s=1) as lease:  # the service is down: a worker writes
            (stored,) = store.get("live", [obj.id])
            assert store.commit("live", [lease], MapChange.writing("live", [stored.replace(version=3)]))
        with UvicornThread(create_app(SETTINGS, store=store, detector=BlobDetector()), port=port):
            resumed = follower.next_of(UpsertEvent, SnapshotEvent, ResetEvent)  # connected again: after version 2
            assert isinstance(resumed, UpsertEvent) and (resumed.object.id, resumed.object.version) == (obj.id, 3)
            follower.stop.set()
            client.send_frame(make_test_frame(2, map_id="live", level=True))
            later = follower.next_of(UpsertEvent)
            assert isinstance(later, UpsertEvent) and later.object.version == 4
            follower.thread.join(10)
            assert not follower.thread.is_alive()


def test_events_of_a_map_not_made_yet_raise_404_or_wait_for_it() -> None:
    """A new user's review: an app that subscribes before its first upload got a 404 at once, while the viewer waits."""
    with UvicornThread(create_app(SETTINGS, detector=BlobDetector())) as server, ArcloudClient(server.url) as client:
        refused = Follower(client, "early")
        with pytest.raises(ServiceError) as caught:
            refused.next_of(SnapshotEvent, timeout_s=10)
        assert caught.value.status == 404
        with ArcloudClient(server.url + "/nowhere") as lost:  # a wrong base URL: no route, raised at once, not waited on
            wrong = Follower(lost, "early", wait_for_map=True)
            with pytest.raises(ServiceError) as no_route:
                wrong.next_of(SnapshotEvent, timeout_s=10)
            assert no_route.value.status == 404 and "no such route" in no_route.value.detail
        waiting = Follower(client, "early", wait_for_map=True)
        assert waiting.received.empty() and waiting.thread.is_alive()  # no map: it waits, raising nothing
        client.send_frame(make_test_frame(0, map_id="early", level=True))
        first = waiting.next_of(SnapshotEvent, UpsertEvent)  # the map's first state once it exists
        assert isinstance(first, (SnapshotEvent, UpsertEvent))
        waiting.stop.set()
        client.send_frame(make_test_frame(1, map_id="early", level=True))
        waiting.thread.join(20)
        assert not waiting.thread.is_alive()
