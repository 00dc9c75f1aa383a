"""``wait_until_processed`` waits on the frames this client sent, not on the map's count: on a map that
already had frames, a client's new frames still pending keep it waiting (it used to return at once). A real
embedded service on uvicorn; the detector holds the frames of device ``late`` until the test lets them go."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import pytest
from svc_helpers import BlobDetector, UvicornThread, make_test_frame

from arcloud.client import ArcloudClient
from arcloud.client.results import FrameCounts
from arcloud.core.types import Detection, Frame
from arcloud.service.settings import Settings
from arcloud.tools.wiring import create_app


class GatedDetector(BlobDetector):
    """``BlobDetector`` that holds each frame of device ``late`` until ``gate`` is set (at most 30 s)."""

    def __init__(self) -> None:
        super().__init__()
        self.gate = threading.Event()

    def detect(self, frame: Frame) -> list[Detection]:
        if frame.device_id == "late":
            self.gate.wait(30)
        return super().detect(frame)


@pytest.fixture
def service() -> Iterator[tuple[str, GatedDetector]]:
    detector = GatedDetector()
    with UvicornThread(create_app(Settings(detector="sim:0", workers=2), detector=detector)) as server:
        yield server.url, detector
        detector.gate.set()


def test_a_client_waits_on_its_own_frames_on_a_map_that_had_others(service: tuple[str, GatedDetector]) -> None:
    url, detector = service
    with ArcloudClient(url) as early, ArcloudClient(url) as late:
        for i in range(6):
            early.send_frame(make_test_frame(i, map_id="busy", device_id="early"))
        assert early.wait_until_processed("busy", timeout_s=20)["frames"] == {"sent": 6, "processed": 6, "failed": 0, "lost": 0}
        for i in range(3):
            late.send_frame(make_test_frame(i, map_id="busy", device_id="late"))
        # The map counts 6 frames done, more than the 3 sent: the old count returned here at once.
        with pytest.raises(
            TimeoutError, match=r"busy: not processed within 0.5 s: 3 of the 3 frames this client sent \(late/f000000: "
        ):
            late.wait_until_processed("busy", timeout_s=0.5)
        with pytest.raises(TimeoutError, match="3 of the 3 frames this client sent"):
            late.wait_until_processed("busy", 3, timeout_s=0.3)  # n_frames: the map's count, met; its own are not
        assert early.wait_until_processed("busy", timeout_s=1)["frames"]["sent"] == 6  # nothing of late's to wait on
        detector.gate.set()
        done = late.wait_until_processed("busy", timeout_s=20)
        assert done == {"map_id": "busy", "frames": {"sent": 3, "processed": 3, "failed": 0, "lost": 0}}
        assert late.stats("busy").frames == FrameCounts(accepted=9, processed=9, failed=0, pending=0)
        assert [late.frame_status("busy", "late", f"f{i:06d}").status for i in range(3)] == ["processed"] * 3
        assert late.send_frame(make_test_frame(0, map_id="busy", device_id="late")).status == "duplicate"
        assert late.wait_until_processed("busy", timeout_s=5)["frames"] == {"sent": 4, "processed": 4, "failed": 0, "lost": 0}


def test_a_frame_the_service_no_longer_knows_counts_lost(service: tuple[str, GatedDetector]) -> None:
    url, _ = service
    with ArcloudClient(url) as device, ArcloudClient(url) as operator:
        device.send_frame(make_test_frame(0, map_id="gone", device_id="early"))
        operator.wait_until_processed("gone", n_frames=1, timeout_s=20)  # a client that sent nothing: the map's count
        operator.delete_map("gone")
        assert device.wait_until_processed("gone", timeout_s=5)["frames"] == {"sent": 1, "processed": 0, "failed": 0, "lost": 1}
        device.send_frame(make_test_frame(1, map_id="gone", device_id="early"))
        device.delete_map("gone")  # through this client: its count starts again
        assert device.wait_until_processed("gone", timeout_s=1)["frames"] == {"sent": 0, "processed": 0, "failed": 0, "lost": 0}
