"""Listing pages and exports are bounded (issue 22): a page of ``GET /v1/maps/{map}/objects`` reads the metadata of
about the objects it returns (before: the whole map's, about 100 ms a page on a 1,500-object map whatever
``limit``), and an export over ``max_export_objects`` objects or ``max_export_voxels`` voxels is refused (422
naming the limit) before any voxel is read, and within them reads its objects a batch at a time (before: a JSON
export with voxels of a 1,500-object map took 26.6 s and 240 MB).

The embedded store counts what each request reads (``CountingStore``); requests go through the real app."""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Sequence
from typing import Any

import pytest
from svc_helpers import AppClient, BlobDetector, cube

from arcloud.core.change import MapChange
from arcloud.core.header import MapHeader
from arcloud.core.types import MapObject, Params
from arcloud.ports import ObjectMeta
from arcloud.service import exports
from arcloud.service.settings import Settings
from arcloud.stores.memory import MemoryStore
from arcloud.tools.wiring import create_app

MAP = "big"
N_OBJECTS = 300
STATS_CAP = 250


class CountingStore(MemoryStore):
    """The embedded store, counting the objects each kind of read returns or is asked for."""

    def __init__(self) -> None:
        super().__init__()
        self.meta_asked = 0  # ids given to object_meta
        self.whole_map_reads = 0  # list_meta / list_objects calls
        self.get_batches: list[int] = []  # ids given to each get

    def reset(self) -> None:
        self.meta_asked, self.whole_map_reads, self.get_batches = 0, 0, []

    def object_meta(self, map_id: str, ids: Sequence[int]) -> list[ObjectMeta]:
        self.meta_asked += len(ids)
        return super().object_meta(map_id, ids)

    def list_meta(self, map_id: str) -> list[ObjectMeta]:
        self.whole_map_reads += 1
        return [o for o in super().list_meta(map_id)]

    def list_objects(self, map_id: str) -> list[MapObject]:
        self.whole_map_reads += 1
        return super().list_objects(map_id)

    def get(self, map_id: str, ids: Sequence[int]) -> list[MapObject]:
        self.get_batches.append(len(ids))
        return super().get(map_id, ids)


@pytest.fixture(scope="module")
def served() -> Iterator[tuple[AppClient, CountingStore]]:
    store = CountingStore()
    store.open_map(MAP, MapHeader.from_params(Params(), codec_version=store.codec_version, created_at_s=1.0))
    objects = [cube(i) for i in range(1, N_OBJECTS + 1)]
    for first in range(0, N_OBJECTS, 50):
        store.commit(MAP, [], MapChange.writing(MAP, objects[first : first + 50]))
    settings = Settings(
        detector="sim:0",
        workers=1,
        key_rate_per_s=0,
        max_export_objects=250,
        max_export_voxels=5000,
        max_stats_objects=STATS_CAP,
    )
    with AppClient(create_app(settings, store=store, detector=BlobDetector())) as client:
        yield client, store


def pages(client: AppClient, **query: Any) -> tuple[list[dict[str, Any]], int]:
    """Every object a paged listing gives with ``query``, and the number of pages."""
    found: list[dict[str, Any]] = []
    cursor, n_pages = None, 0
    while True:
        answer = client.get(f"/v1/maps/{MAP}/objects", params={**query, **({"cursor": cursor} if cursor else {})})
        assert answer.status_code == 200, answer.text
        found += answer.json()["objects"]
        n_pages += 1
        cursor = answer.json()["next_cursor"]
        if cursor is None:
            return found, n_pages


def test_a_page_reads_the_metadata_of_about_the_objects_it_returns(served: tuple[AppClient, CountingStore]) -> None:
    client, store = served
    store.reset()
    answer = client.get(f"/v1/maps/{MAP}/objects", params={"limit": 10})
    assert answer.status_code == 200, answer.text
    page = answer.json()
    assert [o["id"] for o in page["objects"]] == [i for i in range(1, 16) if i % 3][:10]
    assert page["next_cursor"] == str(page["objects"][-1]["id"])
    assert store.whole_map_reads == 0 and store.meta_asked <= 2 * 11, store.meta_asked  # not 300
    store.reset()
    answer = client.get(f"/v1/maps/{MAP}/objects", params={"limit": 10, "cursor": "250"})
    assert [o["id"] for o in answer.json()["objects"]] == [i for i in range(251, 270) if i % 3][:10]
    assert store.whole_map_reads == 0 and store.meta_asked <= 2 * 11, store.meta_asked


@pytest.mark.parametrize(
    "query",
    [{}, {"include": "tentative"}, {"label": "tv"}, {"label": "chair", "min_score": 0.75}, {"bbox": "4,0,0,9.6,1,1"}],
    ids=["served", "tentative", "label", "label-score", "bbox"],
)
def test_pages_walk_the_same_objects_as_one_listing(served: tuple[AppClient, CountingStore], query: dict[str, Any]) -> None:
    client, store = served
    whole = client.get(f"/v1/maps/{MAP}/objects", params=query).json()
    assert whole["next_cursor"] is None and whole["objects"]
    for limit in (3, 100):
        store.reset()
        paged, n_pages = pages(client, limit=limit, **query)
        assert paged == whole["objects"]
        assert n_pages == max(1, math.ceil(len(paged) / limit))
        assert store.whole_map_reads == 0 and store.meta_asked <= 2 * N_OBJECTS
    ids = [o["id"] for o in whole["objects"]]
    assert ids == sorted(ids)


def test_a_bad_cursor_is_refused_naming_it(served: tuple[AppClient, CountingStore]) -> None:
    client, _ = served
    for cursor in ("x", "-1", "1" * 20, "\u0661"):
        answer = client.get(f"/v1/maps/{MAP}/objects", params={"limit": 5, "cursor": cursor})
        assert answer.status_code == 422 and answer.json()["field"] == "cursor", answer.text


def test_exports_over_their_limits_are_refused_naming_the_limit_before_any_voxel_is_read(
    served: tuple[AppClient, CountingStore],
) -> None:
    client, store = served
    served_objects = sum(1 for i in range(1, N_OBJECTS + 1) if i % 3)  # 200: under max_export_objects (250)
    store.reset()
    too_many = client.get(f"/v1/maps/{MAP}/export", params={"format": "glb", "include": "tentative"})
    assert too_many.status_code == 422 and too_many.json()["field"] == "export", too_many.text
    assert "max_export_objects" in too_many.json()["detail"] and f"got {N_OBJECTS} objects" in too_many.json()["detail"]
    for query in ({"format": "ply"}, {"format": "json", "voxels": "true"}):
        too_big = client.get(f"/v1/maps/{MAP}/export", params=query)
        assert too_big.status_code == 422 and too_big.json()["field"] == "export", too_big.text
        detail = too_big.json()["detail"]
        assert "max_export_voxels" in detail and f"got {27 * served_objects} voxels in {served_objects} objects" in detail
    assert store.get_batches == []  # refused before any voxel was read
    plain = client.get(f"/v1/maps/{MAP}/export", params={"format": "json"})
    assert plain.status_code == 200 and len(plain.json()["objects"]) == served_objects
    assert client.get(f"/v1/maps/{MAP}/export", params={"format": "glb"}).status_code == 200


def test_an_export_of_voxels_reads_and_encodes_its_objects_a_batch_at_a_time(served: tuple[AppClient, CountingStore]) -> None:
    client, store = served
    store.reset()
    answer = client.get(f"/v1/maps/{MAP}/export", params={"format": "json", "voxels": "true", "include": "tentative"})
    assert answer.status_code == 422  # 300 objects: over max_export_objects
    objects = [cube(i) for i in range(1, 100) if i % 3][:150]
    body = exports.export_map(MAP, iter(objects), Params(), "json", voxels=True)
    document = json.loads(body)
    assert [o["id"] for o in document["objects"]] == [o.id for o in objects]
    assert all(len(o["voxels"]["centers"]) == 27 for o in document["objects"])
    assert body == json.dumps(json.loads(body)).encode()  # the same bytes one json.dumps of the document gives
    store.reset()
    read = list(exports.read_objects(store, MAP, list(range(1, 201))))
    assert [o.id for o in read] == list(range(1, 201))
    assert store.get_batches == [exports.READ_BATCH] * 3 + [200 - 3 * exports.READ_BATCH]


def test_the_stats_of_a_map_over_the_cap_read_the_status_of_the_cap_and_say_so(served: tuple[AppClient, CountingStore]) -> None:
    client, store = served
    store.reset()
    answer = client.get(f"/v1/maps/{MAP}/stats")
    assert answer.status_code == 200, answer.text
    first = range(1, STATS_CAP + 1)  # every third tentative (cube)
    assert answer.json()["objects"] == {
        "confirmed": sum(i % 3 != 0 for i in first),
        "tentative": sum(i % 3 == 0 for i in first),
        "total": N_OBJECTS,
        "truncated": True,
    }
    assert store.whole_map_reads == 0 and store.meta_asked == STATS_CAP
