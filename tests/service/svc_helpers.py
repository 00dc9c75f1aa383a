"""Helpers of the service tests: small hand-made frames, a detector that finds near blobs in the depth,
a real uvicorn server on a free loopback port, waiting for a condition.

Imported as ``from svc_helpers import ...`` (tests/service is on sys.path; tests/client and
tests/events add it in their conftest).
"""

from __future__ import annotations

import functools
import json
import socket
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from arcloud.core.checks import make_frame
from arcloud.core.types import AABB, N_CLASSES, OBB, Detection, Frame, MapObject, Params
from arcloud.core.voxels import keys_bounds, pack_keys

HEIGHT, WIDTH = 120, 160
INTRINSICS = (130.0, 130.0, 79.5, 59.5)
LEFT, RIGHT = (30, 80, 20, 70), (30, 80, 110, 150)  # near rectangles (rows r0:r1, cols c0:c1) left and right of centre
# A level camera 1 m above the floor looking along world +y (camera x -> world x, y (down) -> -z, z -> y):
# a near rectangle stands upright, 0.77 m wide and tall at 2 m, the size of a chair's front.
LEVEL_CAM2WORLD = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 1.0], [0.0, 0.0, 0.0, 1.0]])


def make_test_frame(
    index: int,
    *,
    map_id: str = "m",
    device_id: str = "d",
    boxes: Sequence[tuple[int, int, int, int]] = (LEFT,),
    near_m: float = 2.0,
    far_m: float = 3.0,
    level: bool = False,
) -> Frame:
    """A 160x120 frame: a far plane with near rectangles (rows r0:r1, cols c0:c1), the camera moved
    1 cm along x per index. Camera axes OpenCV; pose a pure translation (camera axes = world axes, so
    a rectangle lies flat in a z-up world: a box no chair has, never confirmed), or with ``level`` the
    camera of ``LEVEL_CAM2WORLD`` (a rectangle stands upright: a chair's size, confirmed when seen in
    enough frames)."""
    depth = np.full((HEIGHT, WIDTH), far_m, np.float32)
    rgb = np.full((HEIGHT, WIDTH, 3), 90, np.uint8)
    for r0, r1, c0, c1 in boxes:
        depth[r0:r1, c0:c1] = near_m
        rgb[r0:r1, c0:c1] = (200, 60, 40)
    pose = LEVEL_CAM2WORLD.copy() if level else np.eye(4)
    pose[0, 3] = 0.01 * index
    return make_frame(
        rgb, depth, INTRINSICS, pose, timestamp_s=index / 30, map_id=map_id, device_id=device_id, frame_id=f"f{index:06d}"
    )


def multipart_parts(frame: Frame, **meta_changes: Any) -> dict[str, tuple[str, bytes, str]]:
    """httpx ``files=`` for a multipart upload of ``frame`` (JPEG rgb, 16-bit PNG depth in mm)."""
    import cv2

    meta = {
        "device_id": frame.device_id,
        "frame_id": frame.frame_id,
        "timestamp": frame.timestamp_s,
        "intrinsics": {
            "fx": frame.intrinsics.fx,
            "fy": frame.intrinsics.fy,
            "cx": frame.intrinsics.cx,
            "cy": frame.intrinsics.cy,
        },
        "cam2world": frame.cam2world.reshape(16).tolist(),
        "depth_scale": 1000,
    }
    meta.update(meta_changes)
    ok_rgb, rgb = cv2.imencode(".jpg", np.ascontiguousarray(frame.rgb[..., ::-1]))
    ok_depth, depth = cv2.imencode(".png", np.rint(frame.depth_m * 1000).astype(np.uint16))
    assert ok_rgb and ok_depth
    return {
        "meta": ("meta.json", json.dumps(meta).encode(), "application/json"),
        "rgb": ("rgb.jpg", rgb.tobytes(), "image/jpeg"),
        "depth": ("depth.png", depth.tobytes(), "image/png"),
    }


class BlobDetector:
    """Detects each connected region nearer than ``threshold_m`` as one ``label`` instance.
    ``delay_s`` slows every frame down (only those in ``slow_on`` when given); frames whose id is in
    ``crash_on`` raise; in frames whose id is in ``miss_left_on`` the regions left of the image's
    centre go undetected (as a detector misses what it sees); in frames whose id is in ``refuse_on`` it
    reports a class that does not exist (the step refuses it: ``InvalidInput``)."""

    def __init__(
        self,
        label: str = "chair",
        *,
        threshold_m: float = 2.5,
        delay_s: float = 0.0,
        crash_on: Sequence[str] = (),
        slow_on: Sequence[str] | None = None,
        miss_left_on: Sequence[str] = (),
        refuse_on: Sequence[str] = (),
    ) -> None:
        self.label = label
        self.refuse_on = set(refuse_on)
        self.threshold_m = threshold_m
        self.delay_s = delay_s
        self.crash_on = set(crash_on)
        self.slow_on = None if slow_on is None else set(slow_on)
        self.miss_left_on = set(miss_left_on)

    def detect(self, frame: Frame) -> list[Detection]:
        import cv2

        if frame.frame_id in self.crash_on:
            raise RuntimeError(f"detector crashed on {frame.frame_id} (on purpose)")
        if self.delay_s and (self.slow_on is None or frame.frame_id in self.slow_on):
            time.sleep(self.delay_s)
        near = ((frame.depth_m > 0) & (frame.depth_m < self.threshold_m)).astype(np.uint8)
        if frame.frame_id in self.miss_left_on:
            near[:, : frame.shape[1] // 2] = 0
        n, labels = cv2.connectedComponents(near)
        label = "unicorn" if frame.frame_id in self.refuse_on else self.label
        return [Detection(label, 0.9, labels == i) for i in range(1, n) if (labels == i).sum() >= 20]


def make_blob_detector(
    delay_s: float = 0.0, crash_on: Sequence[str] = (), slow_on: Sequence[str] | None = None, miss_left_on: Sequence[str] = ()
) -> BlobDetector:
    """Picklable factory for worker processes (``functools.partial(make_blob_detector, ...)``)."""
    return BlobDetector(delay_s=delay_s, crash_on=crash_on, slow_on=slow_on, miss_left_on=miss_left_on)


def cube(object_id: int, n: int = 3) -> MapObject:
    """An ``n``-voxel cube object (0.05 m voxels) at x = 0.5 m per id; every third tentative, every other a tv."""
    voxel = Params().voxel_size_m
    start = np.array([10 * object_id, 0, 0])
    grid = np.stack(np.meshgrid(*(np.arange(s, s + n) for s in start), indexing="ij"), axis=-1).reshape(-1, 3)
    keys = np.sort(pack_keys(grid))
    lo, hi = keys_bounds(keys, voxel)
    return MapObject(
        id=object_id,
        keys=keys,
        weights=np.ones(keys.size, np.float32),
        votes=np.zeros((keys.size, N_CLASSES), np.float32),
        n_frames=3,
        version=1,
        label="tv" if object_id % 2 else "chair",
        score=0.5 + (object_id % 5) / 10,
        aabb=AABB(lo, hi),
        obb=OBB(center=(lo + hi) / 2, size=hi - lo, rotation=np.eye(3), yaw_rad=0.0),
        bounds=AABB(lo, hi),
        confirmed=object_id % 3 != 0,
    )


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class AppClient:
    """httpx against the ASGI app in this process (no socket), with its lifespan run: the blocking
    methods of ``httpx.Client`` (``get``, ``post``, ``delete``, ``request``) on an event loop in a thread.
    ``address=`` on a request: the client address the app sees (default 127.0.0.1)."""

    def __init__(self, app: Any) -> None:
        self.app = app
        self._from: dict[str, Any] = {}  # client address -> its httpx.AsyncClient

    def __enter__(self) -> AppClient:
        import anyio.from_thread
        import httpx

        self._portal_cm = anyio.from_thread.start_blocking_portal()
        self.portal = self._portal_cm.__enter__()
        self._lifespan = self.app.router.lifespan_context(self.app)
        self.portal.call(self._lifespan.__aenter__)
        self._client = httpx.AsyncClient(transport=httpx.ASGITransport(app=self.app), base_url="http://app")
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            for client in [self._client, *self._from.values()]:
                self.portal.call(client.aclose)
            self.portal.call(self._lifespan.__aexit__, None, None, None)
        finally:
            self._portal_cm.__exit__(None, None, None)

    def request(self, method: str, url: str, *, address: str | None = None, **kwargs: Any) -> Any:
        client = self._client
        if address is not None:
            import httpx

            if address not in self._from:
                transport = httpx.ASGITransport(app=self.app, client=(address, 123))
                self._from[address] = httpx.AsyncClient(transport=transport, base_url="http://app")
            client = self._from[address]
        return self.portal.call(functools.partial(client.request, method, url, **kwargs))

    def get(self, url: str, **kwargs: Any) -> Any:
        return self.request("GET", url, **kwargs)

    def post(self, url: str, **kwargs: Any) -> Any:
        return self.request("POST", url, **kwargs)

    def delete(self, url: str, **kwargs: Any) -> Any:
        return self.request("DELETE", url, **kwargs)


class UvicornThread:
    """A real uvicorn server for ``app`` on 127.0.0.1 in a background thread (lifespan on); ``http``: its HTTP
    protocol (``serve``'s: ``arcloud.service.http_protocol.JsonProblemHTTP``); ``port``: a given one (a restart)."""

    def __init__(self, app: Any, http: Any = "auto", port: int | None = None) -> None:
        import uvicorn

        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        config = uvicorn.Config(app, host="127.0.0.1", port=self.port, log_level="warning", lifespan="on", ws="none", http=http)
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, name="uvicorn", daemon=True)

    def __enter__(self) -> UvicornThread:
        self.thread.start()
        wait_until(lambda: self.server.started, 20.0, "uvicorn to start")
        return self

    def __exit__(self, *exc: object) -> None:
        self.server.should_exit = True
        self.thread.join(20.0)


PROBLEM_MEDIA_TYPE = "application/problem+json"


def assert_problem(response: Any, status: int, field: str | None) -> dict[str, Any]:
    """The RFC 9457 problem of an error answer (httpx's or requests' response), checked: the status, the media
    type, ``type`` (a URI reference), ``title`` and ``detail`` non-empty strings, ``status`` the answer's,
    ``field`` as expected. Returns the problem."""
    assert response.status_code == status, (status, response.status_code, response.text[:500])
    assert response.headers["content-type"] == PROBLEM_MEDIA_TYPE, response.headers
    problem = json.loads(response.content)
    assert isinstance(problem, dict) and {"type", "title", "status", "detail", "field"} <= set(problem), problem
    assert isinstance(problem["type"], str) and (problem["type"].startswith("/problems/") or problem["type"] == "about:blank")
    assert isinstance(problem["title"], str) and problem["title"], problem
    assert isinstance(problem["detail"], str) and problem["detail"] and problem["status"] == status, problem
    assert problem["field"] == field, problem
    return problem


def wait_until(predicate: Callable[[], object], timeout_s: float, what: str, interval_s: float = 0.02) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(interval_s)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def wait_for_subscriber(key: str, *, endpoint: str = "", session: Any = None, timeout_s: float = 10.0) -> None:
    """Wait until a Zenoh subscriber matching ``key`` is known where a put on ``key`` is routed: in ``session``,
    or by the peer listening at ``endpoint`` (asked through a client session of our own, whose puts that peer
    routes). From then on what is put on ``key`` there reaches the subscriber. A key that an earlier subscriber
    matches too tells nothing of a later one: wait for each before declaring the next."""
    from arcloud.events.zenoh import open_session

    probe = session if session is not None else open_session("client", connect=[endpoint])
    publisher = probe.declare_publisher(key)
    try:
        wait_until(lambda: publisher.matching_status.matching, timeout_s, f"a subscriber of {key}", 0.005)
    finally:
        publisher.undeclare()
        if session is None:
            probe.close()


class EventCollector:
    """A Zenoh subscriber's callback keeping every ``arcloud.v1.ObjectEvent`` it is given (Zenoh threads call it)."""

    def __init__(self) -> None:
        self.events: list[Any] = []  # arcloud_pb2.ObjectEvent: the generated module is loaded by the tests that use it
        self._lock = threading.Lock()

    def __call__(self, event: Any) -> None:
        with self._lock:
            self.events.append(event)

    def kinds(self) -> list[int]:
        with self._lock:
            return [e.kind for e in self.events]

    def states(self) -> list[tuple[int, int]]:
        """(version, status) of each event that carries its object's state, in arrival order."""
        with self._lock:
            return [(e.object.version, e.object.status) for e in self.events if e.HasField("object")]

    def of(self, object_id: int) -> list[tuple[int, int]]:
        """``states`` of one object."""
        with self._lock:
            return [(e.object.version, e.object.status) for e in self.events if e.object_id == object_id and e.HasField("object")]
