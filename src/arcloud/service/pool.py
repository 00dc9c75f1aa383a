"""Worker processes beside the API: ``size`` processes (spawned: no state inherited) each running
``target(*args)``, restarted when they die; those that die right after starting are restarted with a
growing delay, so a broken setup does not spawn a process a second. SIGTERM stops a worker after its
current frame. A process whose parent dies (``serve`` killed with SIGKILL, which it cannot catch) stops as if
sent SIGTERM (``run_while_parent_lives``), so a ``serve`` started again does not find the old ones still taking
frames or holding its port.

The target builds its own adapters (a process cannot share the API's connections); the composition root
(``arcloud.tools.wiring``) gives it.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

log = logging.getLogger(__name__)

#: A worker that dies sooner than this after its start failed to start: the next start waits, twice as
#: long each time (up to ``RESTART_MAX_DELAY_S``).
QUICK_EXIT_S = 10.0
RESTART_MAX_DELAY_S = 60.0
_SPAWNING = threading.Lock()  # one spawn at a time changes the environment it passes on
#: How often a process looks whether its parent is alive, and how long it may take to stop once it is not
#: (SIGTERM's graceful stop) before it exits anyway.
PARENT_CHECK_S = 1.0
ORPHAN_EXIT_S = 30.0


def run_while_parent_lives(parent_pid: int, target: Callable[..., None], *args: Any) -> None:
    """``target(*args)`` in this process, with a thread that sends this process SIGTERM when its parent is no
    longer ``parent_pid`` (it died: the process was handed to another), and ends it ``ORPHAN_EXIT_S`` later if that
    did not."""

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(PARENT_CHECK_S)
        log.error("%s: parent process %d is gone; stopping", multiprocessing.current_process().name, parent_pid)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(ORPHAN_EXIT_S)
        os._exit(1)

    threading.Thread(target=watch, name="arcloud-parent-watch", daemon=True).start()
    target(*args)


class WorkerPool:
    """``size`` processes running ``target(*args)`` (a picklable top-level function). ``claim_after_s``:
    how long the frames of a dead worker wait before another claims them (for the log). ``kind``: what
    the processes are, in their names (``arcloud-<kind>-<i>``) and the log (``serve --api-processes``
    runs its API processes in a pool of kind ``api``). ``env``: variables the processes start with besides
    this one's environment."""

    def __init__(
        self,
        size: int,
        target: Callable[..., None],
        args: tuple[Any, ...] = (),
        *,
        claim_after_s: float = 60.0,
        restart: bool = True,
        kind: str = "worker",
        env: Mapping[str, str] | None = None,
    ) -> None:
        self.size = size
        self.env = dict(env or {})
        self.kind = kind
        self.target = target
        self.args = args
        self.claim_after_s = claim_after_s
        self.restart = restart
        self.processes: list[multiprocessing.process.BaseProcess] = []
        self._context = multiprocessing.get_context("spawn")
        self._stopping = threading.Event()
        self._supervisor: threading.Thread | None = None
        self._started_at: dict[int, float] = {}
        self._quick_exits: dict[int, int] = {}  # consecutive quick exits per slot
        self._restart_at: dict[int, float] = {}

    def _spawn(self, index: int) -> multiprocessing.process.BaseProcess:
        process = self._context.Process(
            target=run_while_parent_lives,
            args=(os.getpid(), self.target, *self.args),
            name=f"arcloud-{self.kind}-{index}",
            daemon=False,
        )
        with _SPAWNING:  # a spawned process starts with this one's environment, ``env`` added
            saved = {name: os.environ.get(name) for name in self.env}
            os.environ.update(self.env)
            try:
                process.start()
            finally:
                for name, value in saved.items():
                    if value is None:
                        os.environ.pop(name, None)
                    else:
                        os.environ[name] = value
        return process

    def start(self) -> None:
        self._stopping.clear()
        self.processes = [self._spawn(i) for i in range(self.size)]
        self._started_at = dict.fromkeys(range(self.size), time.monotonic())
        log.info("started %d %s processes: %s", self.size, self.kind, ", ".join(str(p.pid) for p in self.processes))
        if self.restart:
            self._supervisor = threading.Thread(target=self._supervise, name="arcloud-worker-supervisor", daemon=True)
            self._supervisor.start()

    def _supervise(self) -> None:
        while not self._stopping.wait(1.0):
            self.tend(time.monotonic())

    def tend(self, now: float) -> None:
        """Restart the workers found dead (the supervisor calls this every second)."""
        for i, process in enumerate(self.processes):
            if process.is_alive() or self._stopping.is_set():
                continue
            if i not in self._restart_at:  # seen dead for the first time
                quick = now - self._started_at.get(i, now) < QUICK_EXIT_S
                self._quick_exits[i] = self._quick_exits.get(i, 0) + 1 if quick else 0
                delay_s = min(RESTART_MAX_DELAY_S, 2.0 ** self._quick_exits[i]) if quick else 0.0
                self._restart_at[i] = now + delay_s
                claimed = f" (its frames are claimed after {self.claim_after_s:.0f} s)" if self.kind == "worker" else ""
                log.error(
                    "%s process %s exited with %s%s; starting another in %.0f s%s",
                    self.kind,
                    process.pid,
                    process.exitcode,
                    " right after starting" if quick else "",
                    delay_s,
                    claimed,
                )
            if now >= self._restart_at[i]:
                del self._restart_at[i]
                self.processes[i] = self._spawn(i)
                self._started_at[i] = now

    def alive(self) -> int:
        return sum(p.is_alive() for p in self.processes)

    def stop(self, timeout_s: float = 10.0) -> None:
        """SIGTERM every worker (each finishes its frame), wait ``timeout_s``, then kill the rest."""
        self._stopping.set()
        if self._supervisor is not None:
            self._supervisor.join()
        for process in self.processes:
            if process.is_alive():
                process.terminate()
        deadline = time.monotonic() + timeout_s
        for process in self.processes:
            process.join(max(0.0, deadline - time.monotonic()))
            if process.is_alive():
                log.warning("%s process %s did not stop in %.0f s; killing it", self.kind, process.pid, timeout_s)
                process.kill()
                process.join()
        self.processes = []


__all__ = ["ORPHAN_EXIT_S", "PARENT_CHECK_S", "QUICK_EXIT_S", "RESTART_MAX_DELAY_S", "WorkerPool", "run_while_parent_lives"]
