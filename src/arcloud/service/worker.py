"""One ingest worker: frames from a ``FrameQueue``, the per-frame step, the outcome back to the queue.

The same loop runs as a thread beside the API (embedded queue) and in worker processes (Redis queue).
``FrameWorker.run``:

0. With ``warm_up`` (the service's workers), ``warm_up``: what the first frame would otherwise wait for,
   before the worker takes frames or beats. A thread writes the worker's heartbeat every second
   (``heartbeat_s``; off for threads of the API), which also keeps the frame in hand from being taken for
   abandoned. It beats only while the loop reads (its last poll did not fail) or holds a frame: a fresh
   heartbeat says frames get processed.
1. Every ``claim_interval_s``: claim one frame another consumer took ``claim_min_idle_s`` ago without
   settling it (it died or hangs). Beyond ``max_deliveries`` it is a poison frame: dead-lettered (or,
   when a slow delivery did commit it meanwhile, acknowledged as redelivered). Otherwise processed here.
   A frame is given up in the store before it is dead-lettered (``MapStore.give_up_frame``, atomic with the
   commits): the worker that held it, paused past its claim, then has its commit refused (``FrameGivenUp``)
   and settles nothing, so the frame is never both in the map and failed.
2. Take one new frame (blocking ``read_block_s`` while no other frame is in hand), process it.
3. Processing: an undecodable frame is dead-lettered at once; the frame is detected (holding nothing of
   the store); one processed before is acknowledged as redelivered; the map is opened (its header stored by
   the first writer) and refused when its header says other settings than this worker's (``MapMismatch``:
   ``fail``, logged as an error); ``integrate_frame`` (the step after detection) is tried again in place
   on the same detections when locks time out or a lease went stale (nothing was written); then ``ack``.
   ``InvalidInput`` from the detector or the step (the frame's own content is at fault, e.g.
   ``TooManyCells``: its detections span more index cells than a store call takes) is dead-lettered at
   once with its reason: every delivery would fail the same way. Any other error is
   ``fail``: the queue delivers it again later (Redis, until ``max_deliveries``) or counts it failed
   (embedded).

With ``prefetch`` (``ARCLOUD_WORKER_PREFETCH``, off by default) the worker is a pipeline one frame deep: once
the detector is free it takes the next frame and detects it in a thread of its own while this thread
integrates the frame before (query, locks, fusion, commit), so the detector never waits for the store,
nor for other workers' locks on a hot map (onnxruntime releases the GIL while it runs). Two frames are in
hand then, and the heartbeat keeps both fresh; a stop finishes both. Measured in docs/scaling.md.

A frame delivered twice (a worker died after its commit but before its acknowledgement) is not counted
twice: the store's commit records the frame key atomically and refuses a second one; it is acknowledged
as ``redelivered``.

A processed frame is acknowledged with its ``FrameTimings``: the step's time, how long it waited in the
queue (its first delivery: from its acceptance until this worker took it) and how long the step waited in
the store's lock and claim calls (``LockTimer``); the queue counts them in the histograms that
``/metrics`` serves (``arcloud_step_latency_seconds``, ``arcloud_queue_wait_seconds``,
``arcloud_lock_wait_seconds``).
"""

from __future__ import annotations

import contextvars
import functools
import logging
import os
import socket
import threading
import time
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

from arcloud.core.change import MapChange
from arcloud.core.types import Detection, Frame, MapObject, Params
from arcloud.errors import ArcloudError, FrameGivenUp, InvalidInput, LockTimeout, MapMismatch, StaleLease, StoreUnavailable
from arcloud.ports import (
    Detector,
    FrameConsumer,
    FrameTimings,
    Lease,
    MapBeingDeleted,
    MapStore,
    ObjectStore,
    QueuedFrame,
    QueueMonitor,
)
from arcloud.service.change_feed import ChangeFeed
from arcloud.service.logs import log_context
from arcloud.service.map_header import check_map_header, settings_differences, worker_settings

if TYPE_CHECKING:
    import numpy as np

    from arcloud.core.step import StepResult

log = logging.getLogger(__name__)

HEARTBEAT_S = 1.0  # how often a worker writes its heartbeat
LIVE_WORKER_S = 10.0  # a worker whose heartbeat is older is presumed gone

#: Errors after which a step is worth trying again at once: nothing was written.
RETRYABLE = (LockTimeout, StaleLease)

Outcome = Literal["processed", "redelivered", "dead", "failed"]

#: The blank frame ``warm_up`` detects on (VGA, no depth).
WARM_UP_SHAPE = (480, 640)


def warm_up(detector: Detector) -> float:
    """Load what a worker's first frame would otherwise wait for (about 1 s measured: the step's modules
    and scipy, the detector's first run, e.g. an ONNX session's buffers or a simulated room's renderer),
    running the detector on a blank frame. Returns the seconds it took. A detector that cannot take a
    blank frame stays cold (logged): its first frame pays instead."""
    started = time.perf_counter()
    import numpy as np

    from arcloud.core.checks import make_frame
    from arcloud.core.step import process_frame  # noqa: F401 - imported for its modules (scipy)

    height, width = WARM_UP_SHAPE
    blank = make_frame(
        np.zeros((height, width, 3), np.uint8),
        np.zeros((height, width), np.float32),
        (525.0, 525.0, (width - 1) / 2, (height - 1) / 2),
        np.eye(4),
        timestamp_s=0.0,
        map_id="warm-up",
        device_id="warm-up",
        frame_id="0",
    )
    try:
        detector.detect(blank)
    except Exception as exc:  # noqa: BLE001 - a detector of known frames only (e.g. ground-truth masks) stays cold
        log.warning("detector %r did not warm up on a blank frame: %s: %s", detector, type(exc).__name__, exc)
    return time.perf_counter() - started


class LockTimer:
    """``store`` for one frame's step, adding up the seconds its ``lock`` and ``claim`` calls took
    (``lock_wait_s``): what the step waited for objects and index cells, other workers' holds and the
    round trips included. Its commits name the queue entry delivered, ``entry_id`` (refused once that entry
    was given up: ``MapStore.give_up_frame``). Every other call goes straight to ``store``."""

    def __init__(self, store: MapStore, entry_id: str | None = None) -> None:
        self.store = store
        self.entry_id = entry_id
        self.lock_wait_s = 0.0

    def lock(self, map_id: str, ids: Sequence[int], *, ttl_s: float, timeout_s: float) -> Lease:
        started = time.perf_counter()
        try:
            return self.store.lock(map_id, ids, ttl_s=ttl_s, timeout_s=timeout_s)
        finally:
            self.lock_wait_s += time.perf_counter() - started

    def claim(self, map_id: str, cells: Sequence[tuple[int, int, int]], *, ttl_s: float, timeout_s: float) -> Lease:
        started = time.perf_counter()
        try:
            return self.store.claim(map_id, cells, ttl_s=ttl_s, timeout_s=timeout_s)
        finally:
            self.lock_wait_s += time.perf_counter() - started

    def query_region(self, map_id: str, lo: np.ndarray, hi: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        return self.store.query_region(map_id, lo, hi)

    def get(self, map_id: str, ids: Sequence[int]) -> list[MapObject]:
        return self.store.get(map_id, ids)

    def new_ids(self, map_id: str, n: int) -> Sequence[int]:
        return self.store.new_ids(map_id, n)

    def commit(
        self,
        map_id: str,
        leases: Sequence[Lease],
        change: MapChange,
        *,
        frame_key: str | None = None,
        entry_id: str | None = None,
    ) -> bool:
        return self.store.commit(map_id, leases, change, frame_key=frame_key, entry_id=entry_id or self.entry_id)

    def is_frame_done(self, map_id: str, frame_key: str) -> bool:
        return self.store.is_frame_done(map_id, frame_key)

    def give_up_frame(self, map_id: str, frame_key: str, entry_id: str) -> bool:
        return self.store.give_up_frame(map_id, frame_key, entry_id)


def run_step(
    frame: Frame,
    detections: Sequence[Detection],
    store: MapStore,
    params: Params,
    *,
    attempts: int,
) -> tuple[StepResult, int]:
    """``integrate_frame`` of the frame's detections, tried again (at most ``attempts`` times) when locks
    could not be taken or a lease went stale: nothing was written then. Returns the step's result and how
    many retries it took."""
    from arcloud.core.step import integrate_frame  # scipy: loaded with the first frame, not at import

    for attempt in range(1, attempts + 1):
        try:
            return integrate_frame(frame, detections, store, params), attempt - 1
        except FrameGivenUp:  # another worker gave the frame up: no later attempt may write it either
            raise
        except RETRYABLE as exc:
            if attempt == attempts:
                raise
            log.warning("map %s frame %s: %s; trying again (%d/%d)", frame.map_id, frame.key, exc, attempt, attempts)
    raise AssertionError("unreachable")


def timed_detect(detector: Detector, frame: Frame) -> tuple[list[Detection], float]:
    """The frame's detections and the seconds they took."""
    started = time.perf_counter()
    detections = detector.detect(frame)
    return detections, time.perf_counter() - started


@dataclass(frozen=True, slots=True)
class Started:
    """A delivery whose detection runs (in the worker's detector thread) or ran, not yet integrated."""

    item: QueuedFrame
    frame: Frame
    detections: Future[tuple[list[Detection], float]]  # ``timed_detect``'s
    queue_wait_s: float | None  # its first delivery: from its acceptance until this worker took it


def consumer_name(pid: int | None = None) -> str:
    """``<host>-<pid>`` (this process's, or ``pid``'s on this host): unique among the queue's live consumers."""
    return f"{socket.gethostname()}-{os.getpid() if pid is None else pid}"


def of_host(name: str, host: str | None = None) -> bool:
    """Whether the consumer ``name`` is a worker of ``host`` (default: this one): its name less ``-<pid>`` is the host
    (``web-2-555`` is no worker of ``web``)."""
    rest, _, pid = name.rpartition("-")
    return pid.isdigit() and rest == (host or socket.gethostname())


def gone_here(name: str) -> bool:
    """Whether the consumer ``name`` is a worker of this host whose process is no more (its heartbeat is not stale
    yet: a worker killed and started again at once)."""
    if not of_host(name):
        return False
    try:
        os.kill(int(name.rpartition("-")[2]), 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # another user's process: alive
        return False
    return False


def frame_log_fields(item: QueuedFrame) -> dict[str, object]:
    """The log context of a delivery: map, device and frame ids (from the frame key when the frame does
    not decode) and how many times it was delivered."""
    if item.frame is not None:
        device_id, frame_id = item.frame.device_id, item.frame.frame_id
    else:
        device_id, _, frame_id = item.frame_key.rpartition("/")
    return {"map_id": item.map_id, "device_id": device_id, "frame_id": frame_id, "deliveries": item.deliveries}


class FrameWorker:
    """One consumer of a ``FrameQueue``, running the step on what it takes."""

    def __init__(
        self,
        queue: FrameConsumer,
        store: ObjectStore,
        detector: Detector,
        params: Params,
        feed: ChangeFeed | None = None,
        *,
        consumer: str | None = None,
        claim_min_idle_s: float = 60.0,
        claim_interval_s: float = 5.0,
        max_deliveries: int = 5,
        read_block_s: float = 1.0,
        attempts: int = 3,
        heartbeat_s: float | None = HEARTBEAT_S,
        warm_up: bool = False,
        prefetch: bool = False,
        monitor: QueueMonitor | None = None,
    ) -> None:
        self.queue = queue
        self.monitor = monitor  # the queue's live workers: none of other map settings may be running (``check_peers``)
        self.store = store
        self.detector = detector
        self.params = params
        self.feed = feed
        self.consumer = consumer or consumer_name()
        self.claim_min_idle_s = claim_min_idle_s
        self.claim_interval_s = claim_interval_s
        self.max_deliveries = max_deliveries
        self.read_block_s = read_block_s
        self.attempts = attempts
        self.heartbeat_s = heartbeat_s
        self.settings = worker_settings(params, store.codec_version)  # given with every heartbeat
        self._warm_up = warm_up
        self._next_claim = 0.0
        # prefetch: one thread detects the frame taken last while this one integrates the frame before
        self._detector_thread = ThreadPoolExecutor(1, thread_name_prefix="arcloud-detect") if prefetch else None
        self._started: Started | None = None  # prefetch: the frame taken last, detecting or detected
        self._in_hand: tuple[QueuedFrame, ...] = ()  # taken, not settled: kept fresh by the heartbeat
        self._reading = True  # the last poll did not fail: the heartbeat may say so

    def run(self, stop: threading.Event) -> None:
        """Work until ``stop`` is set; the frames in hand are finished first. Every line logged meanwhile in
        this thread carries ``worker`` (this consumer's name)."""
        with log_context(worker=self.consumer):
            self._run(stop)

    def _run(self, stop: threading.Event) -> None:
        try:
            self.queue.prepare()
        except StoreUnavailable as exc:  # the loop waits for the queue; its readers create what is missing
            log.warning("worker %s: cannot prepare the queue yet: %s", self.consumer, exc)
        peers_checked = self._peers_checked(stop)
        if self._warm_up:
            log.info("worker %s warmed up in %.2f s", self.consumer, warm_up(self.detector))
        log.info("worker %s taking frames", self.consumer)
        beating = threading.Event()
        heart = None
        if self.heartbeat_s is not None:
            heart = threading.Thread(target=self._beat, args=(beating,), name="arcloud-heartbeat", daemon=True)
            heart.start()
        try:
            while not stop.is_set():
                if not peers_checked:  # the queue was away at the start: checked before the first frame
                    peers_checked = self._peers_checked(stop)
                    continue
                try:
                    self.poll_once()
                    if not self._reading:
                        log.info("worker %s: polling works again", self.consumer)
                    self._reading = True
                except Exception as exc:  # the queue away for a moment: wait and go on
                    if self._reading:  # the traceback once per outage, then a line a second
                        log.exception("worker %s: polling failed; retrying every second", self.consumer)
                    else:
                        log.warning("worker %s: polling still fails: %s", self.consumer, exc)
                    self._reading = False
                    stop.wait(1.0)
        finally:
            try:
                self.finish_started()
            except Exception:  # the queue away: the frame stays pending, for another delivery
                log.exception("worker %s: the prefetched frame was left for another delivery", self.consumer)
            if self._detector_thread is not None:
                self._detector_thread.shutdown()
            if heart is not None:
                beating.set()
                heart.join()
                try:
                    self.queue.leave(self.consumer)
                except Exception:  # leaving anyway; the heartbeat goes stale
                    log.debug("worker %s: heartbeat not removed", self.consumer, exc_info=True)
        log.info("worker %s stopped", self.consumer)

    def _peers_checked(self, stop: threading.Event) -> bool:
        """``check_peers``; False (after a second's wait) while the queue does not answer."""
        try:
            self.check_peers()
        except StoreUnavailable as exc:
            log.warning("worker %s: cannot read the other workers' settings yet: %s", self.consumer, exc)
            stop.wait(1.0)
            return False
        return True

    def check_peers(self) -> None:
        """``ArcloudError`` when a live worker maps with other map settings (``worker_settings``): this one would fail
        every frame of the maps that one made, each delivered again until it was given up (a review of workers
        failing: good frames dead-lettered); a warning when only their other ``Params`` differ."""
        if self.monitor is None:
            return
        peers = {
            name: theirs
            for name, theirs in self.monitor.live_settings(LIVE_WORKER_S).items()
            if name != self.consumer and not gone_here(name)
        }
        for name, theirs in sorted(peers.items()):
            differences = settings_differences(theirs, self.settings)
            if differences:
                raise ArcloudError(
                    f"worker {self.consumer}: worker {name} maps with other map settings ({'; '.join(differences)}): "
                    "this one would fail every frame of the maps it made; start it with the same --params, or stop "
                    "the others first"
                )
        others = sorted(name for name, theirs in peers.items() if theirs.get("params") != self.settings["params"])
        if others:
            log.warning(
                "worker %s: %s map with other --params (digest %s, ours %s): the maps they share mix both",
                self.consumer, ", ".join(others), peers[others[0]].get("params"), self.settings["params"],
            )  # fmt: skip

    def _beat(self, done: threading.Event) -> None:
        """Write the heartbeat often enough that a long step is never taken for an abandoned one."""
        assert self.heartbeat_s is not None
        interval_s = min(self.heartbeat_s, self.claim_min_idle_s / 3)
        while True:
            try:
                in_hand = self._in_hand
                if self._reading or in_hand:
                    self.queue.heartbeat(self.consumer, in_hand, self.settings)
            except Exception:  # the queue away: the loop logs it; try again next beat
                log.debug("worker %s: heartbeat failed", self.consumer, exc_info=True)
            if done.wait(interval_s):
                return

    def poll_once(self) -> int:
        """Take a frame (an abandoned one when a claim is due, else a new one, blocking ``read_block_s``
        while no other frame is in hand) and start it (``start``). Without prefetch it is then finished;
        with prefetch its detection runs on while the frame started before it is finished here, once the
        detector is free of that one. Returns how many frames were settled."""
        earlier = self._started
        if earlier is not None:
            wait([earlier.detections])  # the detector is free: the next frame may start
        try:
            item = self._next_delivery(block_s=0.0 if earlier is not None else self.read_block_s)
        except BaseException:
            self.finish_started()  # the frame detected is not held through a queue outage
            raise
        later = None if item is None else self.start(item)
        settled = 0
        if isinstance(later, str):  # settled without a step
            settled, later = 1, None
        if self._detector_thread is None:  # no prefetch: the frame just started is finished now
            earlier, later = later, None
        self._started = later
        if earlier is not None:
            self.finish(earlier)
            settled += 1
        return settled

    def finish_started(self) -> None:
        """Finish the frame prefetched (taken and started by ``poll_once``), if any."""
        started, self._started = self._started, None
        if started is not None:
            self.finish(started)

    def _next_delivery(self, *, block_s: float) -> QueuedFrame | None:
        """An abandoned frame when a claim is due and one is there, else a new frame (waiting ``block_s``)."""
        now = time.monotonic()
        if now >= self._next_claim:
            claimed = self.queue.claim_abandoned(self.consumer, min_idle_s=self.claim_min_idle_s)
            if claimed is not None:
                return claimed  # there may be more: look again next time round
            self._next_claim = now + self.claim_interval_s
        return self.queue.take(self.consumer, block_s=block_s)

    def handle(self, item: QueuedFrame) -> Outcome:
        """Process one delivery now (``start``, then ``finish``); returns what became of it."""
        started = self.start(item)
        return started if isinstance(started, str) else self.finish(started)

    def start(self, item: QueuedFrame) -> Started | Outcome:
        """Settle a delivery that needs no step (a poison or undecodable frame); start the detection of
        any other (in the detector thread with prefetch, else now), the frame in hand from here until
        ``finish``. Every line logged meanwhile (here and in the detector) carries the frame's map, device
        and frame ids and its delivery count."""
        with log_context(**frame_log_fields(item)):
            if item.deliveries > self.max_deliveries:
                return self._dead_letter(item, f"delivered {item.deliveries} times (max {self.max_deliveries})")
            if item.frame is None:
                return self._dead_letter(item, f"undecodable: {item.undecodable}")
            queue_wait_s = None
            if item.deliveries == 1 and item.accepted_at_s is not None:  # a later delivery's wait holds the earlier ones
                queue_wait_s = max(0.0, time.time() - item.accepted_at_s)
            self._in_hand = (*self._in_hand, item)
            detect = functools.partial(timed_detect, self.detector, item.frame)
            if self._detector_thread is not None:
                detections = self._detector_thread.submit(contextvars.copy_context().run, detect)
            else:
                detections = Future()
                try:
                    detections.set_result(detect())
                except Exception as exc:  # noqa: BLE001 - settled as the step's errors are, in ``finish``
                    detections.set_exception(exc)
            return Started(item, item.frame, detections, queue_wait_s)

    def finish(self, started: Started) -> Outcome:
        """The rest of a started frame's step (waiting for its detection): integrate its detections into the
        map, then settle it. Logged as ``start``."""
        with log_context(**frame_log_fields(started.item)):
            try:
                return self._finish(started)
            finally:
                self._in_hand = tuple(i for i in self._in_hand if i is not started.item)

    def _finish(self, started: Started) -> Outcome:
        item, frame = started.item, started.frame
        began = time.perf_counter()
        locks = LockTimer(self.store, item.entry_id)
        try:
            detections, detect_s = started.detections.result()
            # A delivery before this one may have committed it; a first delivery is left to the commit, which
            # refuses a frame recorded already (one Redis call a frame fewer).
            if item.deliveries > 1 and self.store.is_frame_done(frame.map_id, frame.key):
                self.queue.ack(item, redelivered=True)
                return "redelivered"
            # The header read (ours stored on the map's first frame); a map without one is checked for a
            # deletion under way, so a frame queued before its DELETE does not bring the map back.
            check_map_header(self.store, frame.map_id, self.params, open_new=True)
            result, retries = run_step(frame, detections, locks, self.params, attempts=self.attempts)
        except FrameGivenUp as exc:  # paused past its claim: another worker gave the frame up and settled it
            log.warning("worker %s: map %s frame %s not written: %s", self.consumer, item.map_id, item.frame_key, exc)
            return "dead"
        except MapMismatch as exc:  # this worker's settings are wrong for the map: leave the frame to others
            log.error("worker %s: map %s frame %s refused: %s", self.consumer, item.map_id, item.frame_key, exc)
            self.queue.fail(item, f"{type(exc).__name__}: {exc}")
            return "failed"
        except InvalidInput as exc:  # every delivery would fail the same way
            return self._dead_letter(item, f"{type(exc).__name__}: {exc}")
        except MapBeingDeleted as exc:  # as would every delivery; the map's keys are going: nothing to give up there
            return self._dead_letter(item, f"{type(exc).__name__}: {exc}", give_up=False)
        except Exception as exc:  # the queue decides: delivered again later, or failed
            log.exception(
                "worker %s: map %s frame %s (device %s) failed (delivery %d of %d)",
                self.consumer,
                item.map_id,
                item.frame_key,
                frame.device_id,
                item.deliveries,
                self.max_deliveries,
            )
            self.queue.fail(item, f"{type(exc).__name__}: {exc}")
            return "failed"
        step_s = detect_s + time.perf_counter() - began  # its own work: not its wait for the frame before
        timings = FrameTimings(step_s=step_s, queue_wait_s=started.queue_wait_s, lock_wait_s=locks.lock_wait_s)
        if self.feed is not None and result.events:
            self._publish(frame.map_id)
        self.queue.ack(item, redelivered=result.skipped, retries=retries, timings=timings)
        outcome: Outcome = "redelivered" if result.skipped else "processed"
        log.debug("worker %s: map %s frame %s %s in %.3f s", self.consumer, item.map_id, item.frame_key, outcome, step_s)
        return outcome

    def _publish(self, map_id: str) -> None:
        """Publish the map's change log up to this commit (and whatever an earlier worker left); a failure is
        logged, not the frame's: the API's sweep publishes it later (``service.change_feed``)."""
        assert self.feed is not None
        try:
            self.feed.publish_pending(map_id)
        except Exception:
            log.warning(
                "worker %s: map %s: publishing its change log failed; the next sweep does", self.consumer, map_id, exc_info=True
            )

    def _dead_letter(self, item: QueuedFrame, reason: str, *, give_up: bool = True) -> Outcome:
        """Give the frame up: first in the store, so that no delivery of its entry commits it after it counts as
        failed (a worker paused past its claim; ``MapStore.give_up_frame``), then to the queue's dead letters. A
        frame some delivery committed already is acknowledged instead: it counts once, as processed. Not in the
        store (``give_up`` False) while the map is being deleted: its mark would outlive the map's keys."""
        if (
            give_up
            and item.map_id
            and item.frame_key
            and not self.store.give_up_frame(item.map_id, item.frame_key, item.entry_id)
        ):
            self.queue.ack(item, redelivered=True)
            return "redelivered"
        log.error(
            "worker %s: map %s frame %s dead-lettered: %s", self.consumer, item.map_id or "?", item.frame_key or "?", reason
        )
        self.queue.dead_letter(item, reason)
        return "dead"


__all__ = [
    "HEARTBEAT_S",
    "LIVE_WORKER_S",
    "FrameWorker",
    "LockTimer",
    "Started",
    "consumer_name",
    "frame_log_fields",
    "gone_here",
    "of_host",
    "run_step",
    "timed_detect",
    "warm_up",
]
