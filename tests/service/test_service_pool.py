"""The processes of a pool stop when their parent dies: `serve` killed with SIGKILL (which it cannot catch) used to
leave its workers taking frames and its API processes holding the port, so a `serve` started again found the port
taken and twice the workers (a review of workers failing)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

#: A parent that starts a pool of two processes which sleep (and print their pids), then waits to be killed.
PARENT = textwrap.dedent(
    """
    import sys, time
    from arcloud.service.pool import WorkerPool
    if __name__ == "__main__":
        pool = WorkerPool(2, time.sleep, (600,), restart=False)
        pool.start()
        print(" ".join(str(p.pid) for p in pool.processes), flush=True)
        time.sleep(600)
    """
)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie is dead too
        return Path(f"/proc/{pid}/stat").read_text().split(") ", 1)[1][0] != "Z"
    except FileNotFoundError:
        return False


def test_a_pools_processes_stop_when_its_parent_is_killed(tmp_path: Path) -> None:
    script = tmp_path / "parent.py"
    script.write_text(PARENT)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    children: list[int] = []
    with subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True, env=env) as parent:
        try:
            assert parent.stdout is not None
            children = [int(pid) for pid in parent.stdout.readline().split()]
            assert len(children) == 2 and all(_alive(pid) for pid in children)
            time.sleep(1.5)  # both children are up and watching
            assert all(_alive(pid) for pid in children)  # a living parent keeps them
            parent.send_signal(signal.SIGKILL)
            parent.wait(10)
            deadline = time.monotonic() + 15
            while any(_alive(pid) for pid in children) and time.monotonic() < deadline:
                time.sleep(0.2)
            assert not any(_alive(pid) for pid in children), f"still running after their parent was killed: {children}"
        finally:
            parent.kill()
            for pid in children:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
