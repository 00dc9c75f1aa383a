"""The viewer in a real browser: headless Chromium (Debian's ``chromium``, driven by Playwright) opens
a viewer ticket's ``/viewer?map=M#ticket=T`` on a real uvicorn server running the embedded service with keys. The page sets
``<body data-objects>`` to the number of boxes it draws; the tests read that count and the screenshot's
pixels (the class colours of viewer.js), and post frames while the page is open.

Frames are those of the service tests: an upright near rectangle left of the image's centre (a chair,
for ``SidedDetector``) and one right of it (a tv), each confirmed after a few frames."""

from __future__ import annotations

import shutil
import time
from collections.abc import Iterator
from typing import Any

import httpx
import numpy as np
import pytest
from svc_helpers import LEFT, RIGHT, UvicornThread, make_test_frame, wait_until
from viewer_helpers import SidedDetector, bearer, make_keys

from arcloud.proto.convert import frame_to_proto
from arcloud.service.settings import Settings
from arcloud.tools.wiring import create_app

CHROMIUM = shutil.which("chromium")
if CHROMIUM is None:
    pytest.skip("chromium not found on PATH (scripts/bootstrap.sh --test installs Debian's chromium)", allow_module_level=True)
playwright_api = pytest.importorskip("playwright.sync_api", reason="playwright is in the dev extra (make installs it)")

PROTOBUF = {"content-type": "application/x-protobuf"}
#: The class colours of viewer.js (CLASS_COLOURS), as RGB.
CHAIR_RGB, TV_RGB = (0xFF, 0x5A, 0x36), (0xC8, 0x6B, 0xFF)
PANEL_PX = 262  # the panel's width (viewer.css --panel-w) and its border: the scene is right of it
WAIT_MS = 15_000  # every wait on the page


class Service:
    def __init__(self, url: str, tokens: dict[str, str]) -> None:
        self.url = url
        self.tokens = tokens
        self.http = httpx.Client(base_url=url, timeout=10.0, headers=bearer(tokens["device"]))
        self.sent: dict[str, int] = {}

    def post(self, map_id: str, n: int, **frame: Any) -> None:
        """``n`` more frames of ``map_id``, and wait until every frame of it was processed."""
        first = self.sent.get(map_id, 0)
        for index in range(first, first + n):
            body = frame_to_proto(make_test_frame(index, map_id=map_id, **frame)).SerializeToString()
            answer = self.http.post(f"/v1/maps/{map_id}/frames", content=body, headers=PROTOBUF)
            assert answer.status_code == 202, answer.text
        self.sent[map_id] = first + n
        wait_until(
            lambda: self.http.get(f"/v1/maps/{map_id}/stats").json()["frames"]["processed"] == first + n,
            30,
            f"the frames of map {map_id} processed",
        )

    def objects(self, map_id: str, **params: str) -> list[dict[str, Any]]:
        return self.http.get(f"/v1/maps/{map_id}/objects", params=params).json()["objects"]  # type: ignore[no-any-return]  # httpx's JSON is Any


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    keys_file = tmp_path_factory.mktemp("keys") / "keys.json"
    tokens = make_keys(
        keys_file, device=("device", "*"), reader=("reader", "room,empty,grows,mixed,picked"), stranger=("reader", "elsewhere")
    )
    settings = Settings(detector="sim:0", workers=1, keys_file=str(keys_file), key_rate_per_s=0, event_poll_s=0.2)
    with UvicornThread(create_app(settings, detector=SidedDetector())) as server:
        service = Service(server.url, tokens)
        service.post("room", 4, level=True, boxes=(LEFT, RIGHT))
        service.post("empty", 2, boxes=())  # a map with frames and no object
        yield service
        service.http.close()


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with playwright_api.sync_playwright() as playwright:
        # Software WebGL (SwiftShader): headless, no GPU.
        chromium = playwright.chromium.launch(
            executable_path=CHROMIUM, args=["--enable-unsafe-swiftshader", "--use-angle=swiftshader"]
        )
        yield chromium
        chromium.close()


@pytest.fixture
def page(browser: Any) -> Iterator[Any]:
    context = browser.new_context(viewport={"width": 1280, "height": 720})
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.requests = []  # (url, Authorization header) of every request the page makes
    page.on("request", lambda request: page.requests.append((request.url, request.headers.get("authorization"))))
    page.set_default_timeout(WAIT_MS)
    yield page
    context.close()
    assert not errors, f"the page raised: {errors}"


def open_viewer(page: Any, service: Service, map_id: str) -> None:
    """Open the viewer as a viewer ticket's link says."""
    drawn = httpx.post(f"{service.url}/v1/maps/{map_id}/viewer-tickets", headers=bearer(service.tokens["reader"]))
    assert drawn.status_code == 201, drawn.text
    page.goto(service.url + drawn.json()["viewer_url"])
    page.wait_for_function("document.body.dataset.state === 'live'")


def wait_drawn(page: Any, n: int) -> None:
    page.wait_for_function(f"document.body.dataset.objects === '{n}'")


def scene_pixels(page: Any) -> np.ndarray:
    """(H, W, 3) int32 RGB of the scene (right of the panel), from a screenshot."""
    import cv2

    png = page.screenshot()
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[:, PANEL_PX:, ::-1].astype(np.int32)  # type: ignore[no-any-return]  # cv2's arrays are Any


def class_pixels(page: Any) -> dict[str, int]:
    """Pixels of the scene (right of the panel) within a small distance of each class colour."""
    image = scene_pixels(page)
    return {
        name: int((np.linalg.norm(image - np.array(rgb), axis=2) < 60).sum())
        for name, rgb in (("chair", CHAIR_RGB), ("tv", TV_RGB))
    }


def test_the_page_draws_the_maps_boxes_in_their_class_colours(page: Any, service: Service) -> None:
    assert len(service.objects("room")) == 2
    open_viewer(page, service, "room")
    wait_drawn(page, 2)
    assert page.evaluate("document.body.dataset.devices") == "1"  # the device's camera
    pixels = class_pixels(page)
    assert pixels["chair"] > 100 and pixels["tv"] > 100, pixels
    labels = page.locator(".label:not(.device)").all_inner_texts()
    assert sorted(text.split()[0] for text in labels) == ["chair", "tv"]
    assert page.url == f"{service.url}/viewer?map=room"  # the used ticket left the address bar
    assert page.evaluate("document.cookie") == ""  # the session's cookie is HttpOnly
    assert [auth for _, auth in page.requests] == [None] * len(page.requests)  # the cookie authenticates


def test_a_key_typed_into_the_form_draws_a_ticket_and_goes_in_no_url(page: Any, service: Service) -> None:
    key = service.tokens["reader"]
    page.goto(f"{service.url}/viewer?map=room")
    page.fill("#key", key)
    page.click("button[type=submit]")
    page.wait_for_function("document.body.dataset.state === 'live'")
    wait_drawn(page, 2)
    assert page.input_value("#key") == ""  # forgotten
    assert page.evaluate("sessionStorage.length + localStorage.length") == 0
    assert all(key not in url for url, _ in page.requests), page.requests
    sent = [url.removeprefix(service.url) for url, auth in page.requests if auth is not None]
    assert sent == ["/v1/maps/room/viewer-tickets"]  # the key's one request


def test_an_empty_map_draws_no_box(page: Any, service: Service) -> None:
    open_viewer(page, service, "empty")
    wait_drawn(page, 0)
    assert class_pixels(page) == {"chair": 0, "tv": 0}


def test_frames_posted_while_the_page_is_open_add_boxes_without_a_reload(page: Any, service: Service) -> None:
    service.post("grows", 4, level=True, boxes=(LEFT,))
    open_viewer(page, service, "grows")
    wait_drawn(page, 1)
    assert class_pixels(page)["tv"] == 0
    page.evaluate("window.loadedOnce = true")
    started = time.monotonic()
    service.post("grows", 4, level=True, boxes=(LEFT, RIGHT))
    wait_drawn(page, 2)
    assert time.monotonic() - started < 10
    assert page.evaluate("window.loadedOnce") is True  # the same page: no reload
    assert class_pixels(page)["tv"] > 100


def set_min_score(page: Any, value: float) -> None:
    page.eval_on_selector(
        "#min-score", "(slider, v) => { slider.value = v; slider.dispatchEvent(new Event('input')); }", str(value)
    )


def test_class_filter_score_slider_tentative_toggle_and_room_points(page: Any, service: Service) -> None:
    service.post("mixed", 4, level=True, boxes=(LEFT, RIGHT))
    service.post("mixed", 1, boxes=(LEFT,))  # a flat box: tentative (never a chair's shape)
    every = service.objects("mixed", include="tentative")
    assert len(every) == 3 and len(service.objects("mixed")) == 2
    open_viewer(page, service, "mixed")
    wait_drawn(page, 2)
    page.wait_for_function("document.body.dataset.voxels === '3'")  # the room's points: every object's, whatever shows
    page.uncheck("#voxels")  # the class pixels below: their colour is near the chair's
    page.wait_for_function("document.body.dataset.voxels === '0' && document.body.dataset.points === '0'")

    page.check("#tentative")
    wait_drawn(page, 3)
    page.uncheck("#tentative")
    wait_drawn(page, 2)

    page.uncheck("input[data-label=chair]")
    wait_drawn(page, 1)
    assert class_pixels(page)["chair"] == 0
    page.check("input[data-label=chair]")
    wait_drawn(page, 2)

    set_min_score(page, 1.0)
    wait_drawn(page, 0)
    set_min_score(page, 0.0)
    wait_drawn(page, 2)

    page.check("#voxels")
    page.wait_for_function("document.body.dataset.voxels === '3'")


def test_a_key_of_another_map_or_a_wrong_token_is_refused_on_the_page(page: Any, service: Service) -> None:
    for token in (service.tokens["stranger"], service.tokens["reader"][:-2] + "xx"):
        page.goto(f"{service.url}/viewer?map=room")
        page.context.clear_cookies()  # no session from a test before
        page.fill("#key", token)
        page.click("button[type=submit]")
        page.wait_for_function("document.body.dataset.state === 'error'")
        assert page.inner_text("#status").startswith("Refused: authorization:")
        assert page.evaluate("document.body.dataset.objects") == "0"


def details(page: Any) -> dict[str, str]:
    """The details panel: id, label and its fields by name."""
    fields = page.eval_on_selector_all("#details dd", "rows => rows.map(row => [row.dataset.field, row.textContent])")
    return {"id": page.inner_text("#details-id"), "label": page.inner_text("#details-label"), **dict(fields)}


def test_a_click_on_a_box_or_its_label_shows_the_objects_details(page: Any, service: Service) -> None:
    by_label = {o["label"]: o for o in service.objects("room")}
    open_viewer(page, service, "room")
    wait_drawn(page, 2)
    assert page.is_hidden("#details")

    chair = page.locator(".label[data-id='{}']".format(by_label["chair"]["id"])).bounding_box()
    page.mouse.click(chair["x"] + chair["width"] / 2, chair["y"] + chair["height"] + 25)  # on the box, under its label
    page.wait_for_function(f"document.body.dataset.selected === '{by_label['chair']['id']}'")
    shown = details(page)
    assert (shown["id"], shown["label"]) == (f"#{by_label['chair']['id']}", "chair")
    assert shown["score"] == f"{by_label['chair']['score']:.2f}" and shown["frames"] == str(by_label["chair"]["n_frames"])

    page.click(".label[data-id='{}']".format(by_label["tv"]["id"]))
    page.wait_for_function(f"document.body.dataset.selected === '{by_label['tv']['id']}'")
    assert details(page)["label"] == "tv"

    page.mouse.click(PANEL_PX + 5, 710)  # the scene's corner: nothing there
    page.wait_for_function("document.body.dataset.selected === ''")
    assert page.is_hidden("#details")
    assert page.evaluate(f"window.arcloudViewer.select({by_label['chair']['id']})") is True
    assert details(page)["label"] == "chair"


def object_labels(page: Any) -> list[dict[str, Any]]:
    """The objects' labels in view (CSS2DRenderer shows them): rectangle and whether decluttering hid it."""
    return page.eval_on_selector_all(  # type: ignore[no-any-return]  # Playwright's JSON is Any
        ".label[data-id]",
        """labels => labels.filter(label => label.style.display !== 'none').map(label => {
             const r = label.getBoundingClientRect();
             return {left: r.left, right: r.right, top: r.top, bottom: r.bottom, hidden: label.classList.contains('overlapped')};
           })""",
    )


def test_labels_that_would_overlap_show_one_of_them(page: Any, service: Service) -> None:
    open_viewer(page, service, "room")
    wait_drawn(page, 2)
    page.uncheck("#cameras")  # only the objects' labels
    # dataset.objects counts the boxes when they are made; CSS2DRenderer puts their labels on the page at the next
    # render, an animation frame later (read at once, a loaded machine's page had none yet)
    page.wait_for_function(
        "[...document.querySelectorAll('.label[data-id]')].filter(l => l.style.display !== 'none').length === 2"
    )
    assert [label["hidden"] for label in object_labels(page)] == [False, False]
    page.mouse.move(800, 400)
    for _ in range(20):  # zoom out until the two labels meet on the screen
        page.mouse.wheel(0, 400)
        page.wait_for_timeout(50)
        labels = object_labels(page)
        if len(labels) == 2 and any(label["hidden"] for label in labels):
            break
    assert [label["hidden"] for label in labels] in ([False, True], [True, False]), labels  # in view, one hidden
    shown, hidden = sorted(labels, key=lambda label: label["hidden"])
    assert hidden["left"] < shown["right"] and shown["left"] < hidden["right"], labels  # the hidden one overlaps it
    assert hidden["top"] < shown["bottom"] and shown["top"] < hidden["bottom"], labels


def test_the_rooms_points_are_drawn_behind_the_boxes_in_their_voxels_colours(page: Any, service: Service) -> None:
    objects = service.objects("room")
    open_viewer(page, service, "room")
    wait_drawn(page, 2)
    n_voxels = sum(o["n_voxels"] for o in objects)
    assert n_voxels > 0
    page.wait_for_function(f"document.body.dataset.points === '{n_voxels}'")  # every voxel: under the cap
    with_points = scene_pixels(page)
    page.uncheck("#voxels")
    page.wait_for_function("document.body.dataset.points === '0'")
    changed = np.abs(with_points - scene_pixels(page)).max(axis=2) > 30
    assert changed.sum() > 100, changed.sum()
    red, _, blue = with_points[changed].T  # the frames' rectangles' colour, VOXEL_RGB, under the faint box faces
    assert (blue > red).mean() < 0.05, np.median(with_points[changed], axis=0)  # none in the tv's class colour (purple)


def test_the_details_follow_the_selected_objects_updates(page: Any, service: Service) -> None:
    service.post("picked", 4, level=True, boxes=(LEFT,))
    [chair] = service.objects("picked")
    open_viewer(page, service, "picked")
    wait_drawn(page, 1)
    assert page.evaluate(f"window.arcloudViewer.select({chair['id']})") is True
    assert details(page)["frames"] == str(chair["n_frames"])
    votes = service.http.get(f"/v1/maps/picked/objects/{chair['id']}").json()["label_votes"]
    assert list(votes) == ["chair"] and votes["chair"] > 0  # SidedDetector: a chair left of the centre, every frame
    page.wait_for_function("document.querySelector('#details dd[data-field=votes]').textContent === 'chair 1.00'")
    service.post("picked", 1, level=True, boxes=(LEFT,))  # an upsert event of the selected object
    page.wait_for_function(f"document.querySelector('#details dd[data-field=frames]').textContent === '{chair['n_frames'] + 1}'")
    page.wait_for_function("document.querySelector('#details dd[data-field=votes]').textContent === 'chair 1.00'")
    assert page.evaluate("document.body.dataset.selected") == str(chair["id"])
