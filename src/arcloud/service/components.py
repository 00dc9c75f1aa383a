"""Adapters chosen from settings: the only place (with the CLI) that names concrete stores and detectors.

Detector specs are those of ``arcloud.detectors.factory`` plus ``sim:SEED`` (the simulator's faulty
detector on ``generate_room(SEED)``, the one ``arcloud replay`` streams frames of), registered here on
first use so that importing the service never loads Open3D.
"""

from __future__ import annotations

import logging
import os
from typing import Any

from arcloud.errors import InvalidInput
from arcloud.ports import Detector, ObjectStore

log = logging.getLogger(__name__)

SIM_PREFIX = "sim"


def _sim_detector(argument: str, *, threads: int = 0) -> Detector:
    """``sim:SEED`` -> ``SimulatedDetector(generate_room(SEED), seed=SEED)`` with the default faults."""
    from arcloud.sim.detector import SimulatedDetector
    from arcloud.sim.room import generate_room

    seed = _sim_seed(argument)
    return SimulatedDetector(generate_room(seed), seed=seed, threads=threads)


def _sim_seed(argument: str) -> int:
    try:
        seed = int(argument)
    except ValueError:
        raise InvalidInput("detector spec", "sim:SEED with SEED a non-negative integer", repr(f"sim:{argument}")) from None
    if seed < 0:
        raise InvalidInput("detector spec", "sim:SEED with SEED a non-negative integer", repr(f"sim:{argument}"))
    return seed


def _registry() -> dict[str, Any]:
    from arcloud.detectors.factory import DETECTOR_FACTORIES, register_detector

    if SIM_PREFIX not in DETECTOR_FACTORIES:
        register_detector(SIM_PREFIX, _sim_detector)
    return DETECTOR_FACTORIES


def threads_per_process(processes: int) -> int:
    """This machine's cores (those this process may run on) shared among ``processes`` worker
    processes: at least one each, so that N workers do not each start a thread per core."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, cores // max(1, processes))


def check_detector_spec(spec: str) -> str:
    """The spec, stripped, if its prefix names a known detector (and ``sim:`` has an integer seed);
    raises ``ValueError`` (``InvalidInput``) otherwise. Loads nothing."""
    if not isinstance(spec, str) or not spec.strip():
        raise InvalidInput("detector", "PREFIX[:ARGUMENT]", repr(spec))
    spec = spec.strip()
    prefix, _, argument = spec.partition(":")
    known = _registry()
    if prefix not in known:
        raise InvalidInput("detector", f"PREFIX[:ARGUMENT] with PREFIX one of {', '.join(sorted(known))}", repr(spec))
    if prefix == SIM_PREFIX:
        _sim_seed(argument)
    return spec


def build_detector(spec: str, *, threads: int | None = None) -> Detector:
    """The detector a spec names, loaded now (models, rooms); ``threads``: its compute threads
    (onnxruntime's intra-op threads, the simulator's ray-casting threads; None: one per core)."""
    from arcloud.detectors.factory import make_detector

    check_detector_spec(spec)
    options: dict[str, Any] = {}
    if threads is not None:
        options["threads" if spec.startswith(SIM_PREFIX) else "intra_op_threads"] = threads
    detector = make_detector(spec, **options)
    log.info("detector %s loaded", spec)
    return detector


def build_store(url: str, *, cell_m: float) -> ObjectStore:
    """``memory`` -> ``MemoryStore``; a Redis URL -> ``RedisStore``."""
    if url == "memory":
        from arcloud.stores.memory import MemoryStore

        return MemoryStore(cell_m=cell_m)
    from arcloud.stores.redis import RedisStore

    return RedisStore(url, cell_m=cell_m)


def close_quietly(thing: object) -> None:
    """Call ``thing.close()`` if it has one, logging (not raising) what goes wrong."""
    close = getattr(thing, "close", None)
    if close is None:
        return
    try:
        close()
    except Exception:  # noqa: BLE001 - shutdown must go on
        log.warning("closing %s failed", type(thing).__name__, exc_info=True)
