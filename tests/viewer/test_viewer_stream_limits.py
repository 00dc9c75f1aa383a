"""Event streams are shared fairly (issue 22): one key holds at most ``max_event_streams_per_key`` streams and one map
``max_event_streams_per_map`` in an API process (429 naming the limit, with Retry-After), beside the process's
``max_event_streams`` (503). Before, one reader key opened the process's 100 streams in 0.88 s and every other map's
viewer got 503. Over real HTTP: uvicorn on 127.0.0.1, the embedded service with a keys file."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import ExitStack

import httpx
import pytest
from svc_helpers import BlobDetector, UvicornThread, make_test_frame, wait_until
from viewer_helpers import EventStream, bearer, make_keys

from arcloud.proto.convert import frame_to_proto
from arcloud.service.event_stream import EventStreams
from arcloud.service.settings import Settings
from arcloud.tools.wiring import create_app

MAX_STREAMS, PER_MAP, PER_KEY = 6, 3, 2


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, dict[str, str], EventStreams]]:
    """(URL, tokens by name, the app's streams) of a service with small stream limits and maps a, b, c."""
    keys_file = tmp_path_factory.mktemp("keys") / "keys.json"
    tokens = make_keys(
        keys_file, device=("device", "*"), hoarder=("reader", "a,b"), neighbour=("reader", "a"), other=("reader", "c")
    )
    settings = Settings(
        detector="sim:0",
        workers=1,
        keys_file=str(keys_file),
        key_rate_per_s=0,
        event_poll_s=0.1,
        max_event_streams=MAX_STREAMS,
        max_event_streams_per_map=PER_MAP,
        max_event_streams_per_key=PER_KEY,
    )
    app = create_app(settings, detector=BlobDetector())
    with UvicornThread(app) as server, httpx.Client(base_url=server.url, timeout=10) as http:
        for map_id in ("a", "b", "c"):
            body = frame_to_proto(make_test_frame(0, map_id=map_id)).SerializeToString()
            headers = {"content-type": "application/x-protobuf", **bearer(tokens["device"])}
            assert http.post(f"/v1/maps/{map_id}/frames", content=body, headers=headers).status_code == 202
        yield server.url, tokens, app.state.event_streams


def refused(url: str, map_id: str, token: str) -> httpx.Response:
    """A stream request that is refused (its answer read whole); fails when the stream opens."""
    with EventStream(url, map_id, token) as stream:
        assert stream.response.status_code != 200, f"a stream of map {map_id} opened"
        stream.response.read()
        return stream.response


def test_one_key_cannot_take_the_processs_streams_from_other_maps_viewers(
    served: tuple[str, dict[str, str], EventStreams],
) -> None:
    url, tokens, streams = served
    with ExitStack() as held:
        opened = []
        answers = []
        for attempt in range(MAX_STREAMS):  # one key asks for every stream of the process
            stream = held.enter_context(EventStream(url, "a" if attempt % 2 else "b", tokens["hoarder"]))
            answers.append(stream.response.status_code)
            if stream.response.status_code == 200:
                opened.append(stream)
            else:
                stream.response.read()
                problem = stream.response.json()
                assert stream.response.headers["retry-after"] == "5"
                assert f"max_event_streams_per_key {PER_KEY}" in problem["detail"], problem
        assert answers == [200] * PER_KEY + [429] * (MAX_STREAMS - PER_KEY)
        for stream in opened:
            stream.next_event("snapshot")
        other = held.enter_context(EventStream(url, "c", tokens["other"]))  # another map's viewer is served
        assert other.response.status_code == 200
        assert other.next_event("snapshot")[0] == "snapshot"
        assert streams.open_streams == PER_KEY + 1 and streams.by_key


def test_one_map_holds_at_most_its_share_of_streams(served: tuple[str, dict[str, str], EventStreams]) -> None:
    url, tokens, streams = served
    wait_until(lambda: streams.open_streams == 0, 5, "the streams of the test before closed")
    with ExitStack() as held:
        for token in (tokens["hoarder"], tokens["hoarder"], tokens["neighbour"]):
            stream = held.enter_context(EventStream(url, "a", token))
            assert stream.response.status_code == 200
        answer = refused(url, "a", tokens["neighbour"])
        assert answer.status_code == 429 and answer.headers["retry-after"] == "5"
        assert (
            f"map 'a' has {PER_MAP} open in this process, the maximum (max_event_streams_per_map {PER_MAP})"
            in (answer.json()["detail"])
        )
        with EventStream(url, "c", tokens["other"]) as other:  # another map is not affected
            assert other.response.status_code == 200
    wait_until(lambda: streams.open_streams == 0 and not streams.by_key, 5, "every stream closed, its places freed")
    with EventStream(url, "a", tokens["neighbour"]) as again:
        assert again.response.status_code == 200
