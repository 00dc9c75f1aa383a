"""Uploads share an API process fairly: ``UploadGate``, one per app, used on the event loop only (no locks).

Why: the per-map rate limit (``map_frame_rate_per_s``, checked before the body is read) never engaged against one
map's flood, because the API decodes fewer frames a second than that limit: the flood held every decoding thread
and the cores, and every other map's uploads waited behind it. Decoding and checking an upload is what costs the
API (a VGA frame about 10 ms of CPU), so that is what the gate shares out:

1. before the body is read, ``admit``: 429 (``Retry-After: 1``) when the upload's map has ``max_uploads_per_map``
   uploads in progress in this process, or its key (with auth none: its client address) ``max_uploads_per_key``
   (in progress: from here until it is queued or refused: its body read, waiting its turn, checked, queued);
2. the body is read (slow clients hold no slot: a trickled body costs a connection, not a core);
3. ``decoding``: the upload waits for a decoding slot (``upload_decode_slots``, default the cores, and one spare),
   maps sharing them: a map alone holds every slot, two maps half each, and so on (``UploadGate.share``); the spare
   slot goes only to a map holding none, so another map's upload does not wait behind a flood's decodes; a freed
   slot goes to the waiting map, within its share, served least recently;
4. it is decoded and checked holding the slot, then queued; when its map has other uploads in progress, both in
   a thread of lower OS priority (``BUSY_MAP_NICE``): a share of slots is not a share of the CPU when the machine
   has less than the slots need (other processes, a small container), and there a map that sends one frame at a
   time (a device) should keep its speed beside one that sends many at once (measured on a loaded 2-core machine:
   another map's decode took 3 to 7 times as long beside a flood's at the same priority).
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import os
import threading
from collections import Counter, deque
from collections.abc import AsyncIterator, Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Annotated, TypeVar

from fastapi import Depends, Request
from starlette.concurrency import run_in_threadpool

from arcloud.service.access import Caller, Refused, require

RETRY_AFTER_S = 1  # what a refused upload is told to wait
BUSY_MAP_NICE = 10  # how much lower (Linux nice) the threads working for maps with several uploads in progress run
BUSY_MAP_THREADS = 32  # at most (started as needed): decoding holds a slot, queueing waits on the queue's store
T = TypeVar("T")


@dataclass(eq=False)
class UploadTicket:
    """An upload admitted: its map and key keep a place until ``close`` (a context manager that closes)."""

    gate: UploadGate
    map_id: str
    key: str
    closed: bool = False

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.gate._leave(self)

    def __enter__(self) -> UploadTicket:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    async def decode(self, work: Callable[[], T]) -> T:
        """``work()`` (decoding and checking the upload) in a worker thread (``run``), holding a decoding slot
        (waiting for the map's turn)."""
        async with self.gate.decoding(self):
            return await self.run(work)

    async def run(self, work: Callable[[], T]) -> T:
        """``work()`` in a worker thread: of lower priority when the map has other uploads in progress
        (``UploadGate.busy_threads``)."""
        if self.gate.by_map[self.map_id] <= 1:
            return await run_in_threadpool(work)
        context = contextvars.copy_context()  # the request's log context, as run_in_threadpool passes it
        return await asyncio.get_running_loop().run_in_executor(self.gate.busy_threads, context.run, work)


class UploadGate:
    """Uploads in progress per map and per key (bounded), and decoding slots shared among maps (module docstring).

    ``slots``: decodes at once (about the cores the API may spend on them), plus one spare that only a map holding
    none may take, so that a map's first upload never waits behind another map's decodes. A map holds at most its
    share, ``slots`` divided among the maps decoding or waiting (rounded up): all of them alone, half of them beside
    one other map. A freed slot goes to the waiting map, within its share, that got one least recently."""

    def __init__(self, *, slots: int, max_per_map: int, max_per_key: int) -> None:
        self.slots = slots
        self.max_per_map = max_per_map
        self.max_per_key = max_per_key
        self.busy = 0  # slots held
        self.held: Counter[str] = Counter()  # slots held per map
        self.by_map: Counter[str] = Counter()  # uploads in progress
        self.by_key: Counter[str] = Counter()
        self._waiting: dict[str, deque[asyncio.Future[None]]] = {}  # map -> its uploads waiting for a slot, in order
        self._served: dict[str, int] = {}  # map -> when it last got a slot (a count of slots given), maps in progress
        self._given = 0
        self._busy_threads: ThreadPoolExecutor | None = None

    @property
    def busy_threads(self) -> ThreadPoolExecutor:
        """The threads that decode and queue uploads of maps with several in progress: of lower OS priority, so that
        under CPU contention a map sending one frame at a time (a device) keeps its speed beside a flood. Started at
        first use (its threads end with the process)."""
        if self._busy_threads is None:
            self._busy_threads = ThreadPoolExecutor(
                BUSY_MAP_THREADS, thread_name_prefix="arcloud-busy-map", initializer=_lower_priority
            )
        return self._busy_threads

    def admit(self, map_id: str, key: str) -> UploadTicket:
        """A place for an upload of ``map_id`` by ``key`` (``Caller.bucket``); ``Refused`` 429 naming the limit."""
        if self.by_map[map_id] >= self.max_per_map:
            raise _busy(
                f"uploads: map {map_id!r} has {self.by_map[map_id]} uploads in progress in this API process, the most it "
                f"may (max_uploads_per_map {self.max_per_map})",
                "map_id",
            )
        if self.by_key[key] >= self.max_per_key:
            who = f"key {key.removeprefix('key:')}" if key.startswith("key:") else f"client {key.removeprefix('ip:')}"
            raise _busy(
                f"uploads: {who} has {self.by_key[key]} uploads in progress in this API process, the most it may "
                f"(max_uploads_per_key {self.max_per_key})",
                "authorization",
            )
        self.by_map[map_id] += 1
        self.by_key[key] += 1
        return UploadTicket(self, map_id, key)

    def _leave(self, ticket: UploadTicket) -> None:
        for counts, name in ((self.by_map, ticket.map_id), (self.by_key, ticket.key)):
            counts[name] -= 1
            if counts[name] <= 0:
                del counts[name]
        if ticket.map_id not in self.by_map:
            self._served.pop(ticket.map_id, None)

    @asynccontextmanager
    async def decoding(self, ticket: UploadTicket) -> AsyncIterator[None]:
        """Hold a decoding slot (waiting for the map's turn) while the block runs."""
        await self._acquire(ticket.map_id)
        try:
            yield
        finally:
            self._release(ticket.map_id)

    def share(self, map_id: str) -> int:
        """The most slots ``map_id`` may hold now: ``slots`` over the maps decoding or waiting, itself included."""
        active = len(self.held.keys() | self._waiting.keys() | {map_id})
        return max(1, -(-self.slots // active))

    def _may_take(self, map_id: str) -> bool:
        held = self.held[map_id]
        if held >= self.share(map_id):
            return False
        return self.busy < self.slots or (held == 0 and self.busy < self.slots + 1)  # the spare: for a map holding none

    async def _acquire(self, map_id: str) -> None:
        if map_id not in self._waiting and self._may_take(map_id):
            self._take(map_id)
            return
        waiter: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._waiting.setdefault(map_id, deque()).append(waiter)
        try:
            await waiter
        except asyncio.CancelledError:
            if waiter.done() and not waiter.cancelled():
                self._release(map_id)  # given a slot as it was cancelled: hand it on
            else:
                queue = self._waiting.get(map_id)
                if queue is not None and waiter in queue:
                    queue.remove(waiter)
                    if not queue:
                        del self._waiting[map_id]
                self._grant()  # the map may have left: the others' shares grew
            raise

    def _take(self, map_id: str) -> None:
        self.busy += 1
        self.held[map_id] += 1
        self._given += 1
        if map_id in self.by_map:
            self._served[map_id] = self._given

    def _release(self, map_id: str) -> None:
        self.busy -= 1
        self.held[map_id] -= 1
        if self.held[map_id] <= 0:
            del self.held[map_id]
        self._grant()

    def _grant(self) -> None:
        """Give free slots to waiting uploads: each time to the map, among those within their share, served least
        recently (never: first), first come first served within a map."""
        while True:
            ready = [m for m in self._waiting if self._may_take(m)]
            if not ready:
                return
            map_id = min(ready, key=lambda m: self._served.get(m, -1))
            queue = self._waiting[map_id]
            waiter = queue.popleft()
            if not queue:
                del self._waiting[map_id]
            if waiter.done():  # cancelled while it waited
                continue
            self._take(map_id)
            waiter.set_result(None)


def _lower_priority() -> None:
    """Run this thread ``BUSY_MAP_NICE`` lower than it started (Linux sets nice per thread; elsewhere nothing changes):
    lower than the process, also where it was started niced (an absolute 10 left a process started at nice 10 as it was)."""
    with contextlib.suppress(AttributeError, OSError):  # no per-thread priority here: the threads run as the others
        thread = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, thread, min(19, os.getpriority(os.PRIO_PROCESS, thread) + BUSY_MAP_NICE))


def _busy(detail: str, field: str) -> Refused:
    return Refused(429, f"{detail}; retry in {RETRY_AFTER_S} s", field, {"Retry-After": str(RETRY_AFTER_S)})


def usable_cores() -> int:
    """The cores this process may run on (its affinity: a container's or taskset's), else the machine's."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def upload_gate(request: Request) -> UploadGate:
    """The app's gate, made from its settings at its first upload (on the event loop: no race)."""
    gate: UploadGate | None = getattr(request.app.state, "upload_gate", None)
    if gate is None:
        settings = request.app.state.runtime.settings
        gate = UploadGate(
            slots=settings.upload_decode_slots or usable_cores(),  # the spare is the gate's own
            max_per_map=settings.max_uploads_per_map,
            max_per_key=settings.max_uploads_per_key,
        )
        request.app.state.upload_gate = gate
    return gate


_may_write = require("write")  # one instance: FastAPI runs a dependency once a request, this one included


async def admit_upload(request: Request, caller: Annotated[Caller, Depends(_may_write)]) -> AsyncIterator[UploadTicket]:
    """The dependency of the upload route (async: on the event loop, as the gate wants): access checked
    (``require("write")``), then a place for the upload, held until the request ends; 429 before the body is read
    when its map or key has no place left."""
    map_id = request.path_params["map_id"]
    with upload_gate(request).admit(map_id, caller.bucket) as ticket:
        yield ticket


__all__ = ["UploadGate", "UploadTicket", "admit_upload", "upload_gate"]
