"""The SDK against a real uvicorn server on loopback: blocking and asyncio clients, errors, waiting,
the served map (confirmed objects) against every object, and the Zenoh subscription."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from dataclasses import replace

import numpy as np
import pytest
from svc_helpers import BlobDetector, EventCollector, UvicornThread, free_port, make_test_frame, wait_for_subscriber

from arcloud.client import ArcloudClient, AsyncArcloudClient, ServiceError
from arcloud.client.results import FrameAccepted, FrameCounts, FrameState, MapDeleted, ObjectCounts
from arcloud.events.zenoh import object_key, tentative_key
from arcloud.proto.arcloud.v1 import arcloud_pb2 as pb
from arcloud.service.settings import Settings
from arcloud.tools.wiring import create_app


@pytest.fixture(scope="module")
def server() -> Iterator[tuple[str, str]]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = Settings(detector="sim:0", workers=2, zenoh_mode="peer", zenoh_listen=[endpoint])
    with UvicornThread(create_app(settings, detector=BlobDetector(refuse_on=["refused"]))) as running:
        yield running.url, endpoint


def test_blocking_client_round_trip(server: tuple[str, str]) -> None:
    url, endpoint = server
    served, everything = EventCollector(), EventCollector()

    with ArcloudClient(url) as client:
        subscriptions = [client.subscribe("c1", served, [endpoint])]
        try:  # each known to the service's peer before the next (a key tells of all before)
            wait_for_subscriber(object_key("c1", 0), endpoint=endpoint)
            subscriptions.append(client.subscribe("c1", everything, [endpoint], include_tentative=True))
            wait_for_subscriber(tentative_key("c1", 0), endpoint=endpoint)
            first = client.send_frame(make_test_frame(0, map_id="c1", level=True))
            assert first == FrameAccepted(map_id="c1", device_id="d", frame_id="f000000", status="queued")
            frame = make_test_frame(1, map_id="c1", level=True)
            depth_mm = np.rint(frame.depth_m * 1000).astype(np.uint16)
            sent = client.send_frame(
                map_id="c1",
                rgb=frame.rgb,
                depth=depth_mm,
                intrinsics=(130.0, 130.0, 79.5, 59.5),
                cam2world=frame.cam2world,
                timestamp_s=1.0,
                device_id="d2",
                frame_id="x1",
                depth_scale=1000.0,
            )
            assert sent.status == "queued" and sent.device_id == "d2"
            done = client.wait_until_processed("c1", timeout_s=20)
            assert done == {"map_id": "c1", "frames": {"sent": 2, "processed": 2, "failed": 0, "lost": 0}}
            assert client.stats("c1").frames == FrameCounts(accepted=2, processed=2, failed=0, pending=0)
            (tentative,) = client.list_objects("c1", include_tentative=True)
            assert tentative.status == "tentative" and client.list_objects("c1") == []  # two frames: not yet served
            assert client.get_object("c1", tentative.id).status == "tentative"
            for i in (2, 3, 4):
                client.send_frame(make_test_frame(i, map_id="c1", level=True))
            assert client.wait_until_processed("c1", timeout_s=20)["frames"]["processed"] == 5
            deadline = time.monotonic() + 10
            while (not everything.events or everything.events[-1].object.version < 5) and time.monotonic() < deadline:
                time.sleep(0.02)
            time.sleep(0.2)
        finally:
            for subscription in subscriptions:
                subscription.close()

        (obj,) = client.list_objects("c1")
        assert obj.n_devices == 2 and obj.n_frames == 5 and obj.status == "confirmed" and obj.id == tentative.id
        assert client.list_objects("c1", include_tentative=True) == [obj]
        # Zenoh: every state to who asked for tentative objects too; the served map's subscriber from confirmation on.
        versions = [v for v, _ in everything.states()]  # two workers: a state routed after a newer one is dropped
        assert versions == sorted(set(versions)) and everything.states()[-1] == (5, pb.Object.STATUS_CONFIRMED)
        confirmed = [(v, s) for v, s in everything.states() if s == pb.Object.STATUS_CONFIRMED]
        assert [(v, s) for v, s in served.states() if s == pb.Object.STATUS_CONFIRMED] == confirmed and served.states()[-1] == (
            5,
            pb.Object.STATUS_CONFIRMED,
        )
        assert all(e.map_id == "c1" and e.object_id == obj.id for e in everything.events)
        assert client.list_objects("c1", label="tv") == []
        assert obj.aabb is not None and client.list_objects("c1", bbox=(*obj.aabb.min, *obj.aabb.max))[0].id == obj.id
        detail = client.get_object("c1", obj.id, voxels=True)
        assert detail.voxels is not None and len(detail.voxels.centers) == obj.n_voxels
        assert list(detail.label_votes) == ["chair"] and detail.label_votes["chair"] > 0  # every frame a chair

        with pytest.raises(ServiceError) as refused:
            client.send_frame(make_test_frame(2, map_id="other"), map_id="c1")  # body and path disagree
        assert refused.value.status == 422 and refused.value.field == "map_id"
        with pytest.raises(ServiceError) as missing:
            client.get_object("c1", 12345)
        assert missing.value.status == 404
        with pytest.raises(TimeoutError, match="not processed within 0.3 s: 6 frames of the map in all"):
            client.wait_until_processed("c1", 6, timeout_s=0.3)  # every client's: 5 are all there will be
        assert client.frame_status("c1", "d2", "x1") == FrameState(map_id="c1", device_id="d2", frame_id="x1", status="processed")
        with pytest.raises(ServiceError) as never:
            client.frame_status("c1", "d", "never-sent")
        assert never.value.status == 404
        with pytest.raises(ServiceError) as bad_id:
            client.frame_status("c1", "d", "f*")
        assert bad_id.value.status == 422 and bad_id.value.field == "frame_id"
        assert client.delete_map("c1") == MapDeleted(map_id="c1", deleted_objects=1)
        with pytest.raises(ServiceError) as gone:
            client.stats("c1")
        assert gone.value.status == 404


def test_async_client_with_concurrent_users(server: tuple[str, str]) -> None:
    url, _ = server

    async def run() -> tuple[list[dict], dict, list[dict]]:
        async with AsyncArcloudClient(url) as client:

            async def user(k: int) -> list[dict]:
                return [
                    await client.send_frame(make_test_frame(i, map_id="c2", device_id=f"user-{k}"))
                    for i in range(k * 3, k * 3 + 3)
                ]

            answers = [a for batch in await asyncio.gather(*(user(k) for k in range(3))) for a in batch]
            await client.send_frame(replace(make_test_frame(9, map_id="c2", device_id="user-0"), frame_id="refused"))
            done = await client.wait_until_processed("c2", timeout_s=30)
            assert done["frames"] == {"sent": 10, "processed": 9, "failed": 1, "lost": 0}
            stats = await client.stats("c2")
            refused = await client.frame_status("c2", "user-0", "refused")  # InvalidInput from the step: failed at once
            assert (
                refused.status == "failed"
                and refused.reason is not None
                and refused.reason.startswith("InvalidInput: detections[0].label")
            )
            assert await client.list_objects("c2", min_score=0.0) == []  # lying flat: never confirmed
            objects = await client.list_objects("c2", min_score=0.0, include_tentative=True)
            with pytest.raises(ServiceError):
                await client.get_object("c2", 999)
            with pytest.raises(ServiceError) as refused:
                await client.list_objects("c2", label="dog")
            assert refused.value.status == 422 and refused.value.field == "label"
            await client.delete_map("c2")
            return answers, stats, objects

    answers, stats, objects = asyncio.run(run())
    assert [a.status for a in answers] == ["queued"] * 9
    assert (
        stats.frames.processed == 9
        and stats.frames.failed == 1
        and stats.objects == ObjectCounts(confirmed=0, tentative=1, total=1, truncated=False)
    )
    assert len(objects) == 1 and objects[0].n_devices == 3 and objects[0].status == "tentative"
