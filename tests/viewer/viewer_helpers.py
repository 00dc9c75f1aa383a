"""Helpers of the viewer tests: a detector that tells classes apart, server-sent events read over real HTTP,
a keys file with tokens.

Imported as ``from viewer_helpers import ...`` (tests/viewer is on sys.path as the tests' folder).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from svc_helpers import BlobDetector

from arcloud.access import new_key
from arcloud.core.types import Detection, Frame
from arcloud.stores.file_api_keys import FileKeyStore


class SidedDetector(BlobDetector):
    """``BlobDetector``, but a region left of the image's centre is a chair and one right of it a tv."""

    def detect(self, frame: Frame) -> list[Detection]:
        width = frame.shape[1]
        out = []
        for found in super().detect(frame):
            columns = np.nonzero(found.mask)[1]
            out.append(Detection("chair" if columns.mean() < width / 2 else "tv", found.score, found.mask))
        return out


def make_keys(path: Path, **maps_by_name: tuple[str, str]) -> dict[str, str]:
    """A keys file at ``path`` with one key per ``name=(role, maps)``; their tokens by name."""
    keys = FileKeyStore(path)
    tokens = {}
    for name, (role, maps) in maps_by_name.items():
        key, token = new_key(role, tuple(maps.split(",")), now_s=time.time(), name=name)
        keys.add(key)
        tokens[name] = token
    keys.close()
    return tokens


def bearer(token: str) -> dict[str, str]:
    return {"authorization": f"Bearer {token}"}


def version_of(event_id: str | None) -> int | None:
    """The map's version an event id names (``V`` or ``V@B``: ``event_stream.event_id``)."""
    return None if event_id is None else int(event_id.split("@")[0])


class EventStream:
    """``GET /v1/maps/{map}/events`` over real HTTP, read event by event; every wait bounded."""

    def __init__(
        self,
        base_url: str,
        map_id: str,
        token: str | None = None,
        *,
        tentative: bool = False,
        cookies: dict[str, str] | None = None,
        last_event_id: str | None = None,
    ) -> None:
        self.client = httpx.Client(base_url=base_url, timeout=httpx.Timeout(10.0, read=5.0), cookies=cookies)
        params = {"include": "tentative"} if tentative else {}
        headers = {**(bearer(token) if token else {}), **({"last-event-id": last_event_id} if last_event_id else {})}
        self._cm = self.client.stream("GET", f"/v1/maps/{map_id}/events", params=params, headers=headers)
        self.response = self._cm.__enter__()
        self._lines = self.response.iter_lines()
        self.objects: dict[int, dict[str, Any]] = {}
        self.devices: dict[str, dict[str, Any]] = {}
        self.log: list[tuple[str, Any]] = []
        self.last_id: str | None = None  # the last event id taken (a browser's ``lastEventId``)

    def __enter__(self) -> EventStream:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._cm.__exit__(None, None, None)
        self.client.close()

    def events(self) -> Iterator[tuple[str, Any]]:
        """(name, data) of each event, applied to ``objects`` and ``devices``; comments as (":", text); ends
        with the stream."""
        name, data, event_id = "message", [], None
        for line in self._lines:
            if not line:
                if event_id is not None:
                    self.last_id = event_id
                if data:
                    self._apply(name, json.loads("\n".join(data)))
                    yield self.log[-1]
                name, data, event_id = "message", [], None
            elif line.startswith(":"):
                yield ":", line[1:].strip()
            else:
                field, _, value = line.partition(":")
                value = value.removeprefix(" ")
                if field == "event":
                    name = value
                elif field == "data":
                    data.append(value)
                elif field == "id":
                    event_id = value

    def read_until(self, done: Callable[[EventStream], bool], what: str, timeout_s: float = 15.0) -> None:
        """Read events until ``done(self)`` (on ``objects`` and ``devices``, which they keep up to date)."""
        deadline = time.monotonic() + timeout_s
        for _ in self.events():
            if done(self):
                return
            if time.monotonic() > deadline:
                break
        raise AssertionError(f"timed out after {timeout_s} s (or the stream ended) waiting for {what}; got {self.log}")

    def _apply(self, name: str, data: Any) -> None:
        """Keep ``objects``, ``devices`` and ``log`` as a viewer keeps its state."""
        self.log.append((name, data))
        if name == "snapshot":
            self.objects = {o["id"]: o for o in data["objects"]}
            self.devices = {d["device_id"]: d for d in data["devices"]}
        elif name == "upsert":
            self.objects[data["id"]] = data
        elif name == "removed":
            del self.objects[data["id"]]
        elif name == "device":
            self.devices[data["device_id"]] = data
        elif name == "device_removed":
            del self.devices[data["device_id"]]

    def next_event(self, *names: str, timeout_s: float = 15.0) -> tuple[str, Any]:
        """The next event named one of ``names`` (any event when none), within ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        for name, data in self.events():
            if not names or name in names:
                return name, data
            if time.monotonic() > deadline:
                break
        raise AssertionError(f"no {' or '.join(names) or 'event'} within {timeout_s} s (or the stream ended)")
