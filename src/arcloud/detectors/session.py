"""onnxruntime sessions: one per process per (model file, thread count), CPU provider, full graph
optimisation; load failures and signature mismatches become ``ModelError`` saying expected vs got.

onnxruntime is imported on first use, never at import time.
"""

from __future__ import annotations

import logging
import os
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from arcloud.core.checks import describe
from arcloud.errors import InvalidInput, ModelError

if TYPE_CHECKING:
    import onnxruntime

log = logging.getLogger(__name__)

_sessions: dict[tuple[str, int, int | None, tuple[str, ...]], onnxruntime.InferenceSession] = {}
_sessions_lock = threading.Lock()


@dataclass(frozen=True, slots=True)
class TensorSpec:
    """Name, shape (ints for fixed dims, str/None for dynamic ones) and element type of a model tensor."""

    name: str
    shape: tuple[int | str | None, ...]
    type: str

    def __str__(self) -> str:
        dims = ",".join("?" if not isinstance(d, int) else str(d) for d in self.shape)
        return f"{self.name} {self.type}[{dims}]"


def load_session(
    model_path: str | os.PathLike[str], *, intra_op_threads: int | None = None, execution_provider: str = "cpu"
) -> onnxruntime.InferenceSession:
    """The process-wide session of ``model_path`` (created on first call, then cached).

    ``intra_op_threads``: threads for one operator (None: onnxruntime's default, one per core).
    ``execution_provider``: ``cpu``, ``cuda`` (onnxruntime-gpu's CUDA provider, CPU for what it lacks), or
    ``auto`` (CUDA when this onnxruntime has it and a GPU answers, else CPU).
    Raises ``ModelError`` when the file is missing or is not a loadable ONNX model, or CUDA was asked for
    and is not there.
    """
    path = Path(model_path)
    if not path.is_file():
        raise ModelError(f"model file: expected an ONNX file, got no file at {path}")
    if intra_op_threads is not None and (not isinstance(intra_op_threads, int) or intra_op_threads < 1):
        raise InvalidInput("intra_op_threads", "an int >= 1 or None", describe(intra_op_threads))
    providers = execution_providers(execution_provider)
    resolved = path.resolve()
    key = (str(resolved), resolved.stat().st_mtime_ns, intra_op_threads, providers)
    with _sessions_lock:
        session = _sessions.get(key)
        if session is None:
            session = _create_session(resolved, intra_op_threads, providers)
            _sessions[key] = session
    return session


#: ``execution_provider`` names -> what ``execution_providers`` may answer.
EXECUTION_PROVIDERS = ("cpu", "cuda", "auto")
CUDA = "CUDAExecutionProvider"
CPU = "CPUExecutionProvider"


def execution_providers(name: str) -> tuple[str, ...]:
    """onnxruntime's provider list for ``cpu``, ``cuda`` or ``auto`` (``ModelError`` for ``cuda`` without it)."""
    import onnxruntime as ort

    if name not in EXECUTION_PROVIDERS:
        raise InvalidInput("execution_provider", f"one of {', '.join(EXECUTION_PROVIDERS)}", repr(name))
    available = ort.get_available_providers()
    if name == "cpu" or (name == "auto" and CUDA not in available):
        return (CPU,)
    if CUDA not in available:
        raise ModelError(
            f"execution provider cuda: this onnxruntime ({ort.__version__}) has no CUDAExecutionProvider (it has "
            f"{', '.join(available)}); install onnxruntime-gpu in place of onnxruntime, on a machine with CUDA"
        )
    return (CUDA, CPU)


def _create_session(path: Path, intra_op_threads: int | None, providers: tuple[str, ...]) -> onnxruntime.InferenceSession:
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.inter_op_num_threads = 1
    options.log_severity_level = 3  # errors only; warnings about unused initialisers are noise
    if intra_op_threads is not None:
        options.intra_op_num_threads = intra_op_threads
    try:
        session = ort.InferenceSession(str(path), sess_options=options, providers=list(providers))
    except Exception as exc:  # onnxruntime raises its own untyped errors (InvalidProtobuf, Fail, ...)
        raise ModelError(f"model file {path}: expected a loadable ONNX model, got {type(exc).__name__}: {exc}") from exc
    if providers[0] == CUDA and session.get_providers()[0] != CUDA:  # onnxruntime falls back when CUDA fails to start
        raise ModelError(f"model file {path}: the CUDA execution provider did not start (got {session.get_providers()})")
    log.info(
        "loaded ONNX model %s (%s; intra_op_threads=%s, providers %s)",
        path,
        describe_signature(session),
        intra_op_threads,
        session.get_providers(),
    )
    return session


def _spec(node: Any) -> TensorSpec:
    shape = node.shape if isinstance(node.shape, list) else []
    return TensorSpec(node.name, tuple(shape), node.type)


def input_specs(session: onnxruntime.InferenceSession) -> list[TensorSpec]:
    return [_spec(node) for node in session.get_inputs()]


def output_specs(session: onnxruntime.InferenceSession) -> list[TensorSpec]:
    return [_spec(node) for node in session.get_outputs()]


def metadata(session: onnxruntime.InferenceSession) -> dict[str, str]:
    """The model's custom metadata (Ultralytics puts ``names``, ``imgsz``, ``task`` there)."""
    return dict(session.get_modelmeta().custom_metadata_map)


def describe_signature(session: onnxruntime.InferenceSession) -> str:
    """ "inputs: images tensor(float)[1,3,640,640]; outputs: output0 ..., output1 ..." for messages."""
    inputs = ", ".join(str(s) for s in input_specs(session)) or "none"
    outputs = ", ".join(str(s) for s in output_specs(session)) or "none"
    return f"inputs: {inputs}; outputs: {outputs}"


def signature_error(model_path: object, adapter: str, expected: str, session: onnxruntime.InferenceSession) -> ModelError:
    """A ``ModelError`` for a model that does not fit an adapter: what it expected, what the model has."""
    got = describe_signature(session)
    return ModelError(f"model {model_path} does not fit the {adapter} adapter: expected {expected}, got {got}")
