"""Detectors by spec string: ``make_detector("onnx:models/yolov8n-seg.onnx", score_threshold=0.3)``.

A spec is ``PREFIX`` or ``PREFIX:ARGUMENT``. Built in:
- ``onnx:PATH``: an ONNX model; a torchvision Mask R-CNN export (outputs boxes, labels, scores,
  masks) is recognised by its outputs, anything else is taken as Ultralytics YOLO-seg.
  ``onnx`` alone uses the model named by the ``ARCLOUD_MODEL`` environment variable, else the
  catalogue's default model in the model cache (``detectors.catalogue``: ``arcloud models pull``).
- ``maskrcnn:PATH``: a torchvision Mask R-CNN export.
- ``@cpu``, ``@cuda`` or ``@auto`` after a model's path picks onnxruntime's execution provider
  (``onnx:models/y.onnx@cuda``; default cpu; ``auto``: CUDA when there, else CPU).

Other modules add their own (``sim``, ``gt-masks``, ...) with ``register_detector(prefix, factory)``;
a factory is called as ``factory(argument, **options)`` with the text after the first ':' ("" if none).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

from arcloud.errors import InvalidInput
from arcloud.ports import Detector

#: The environment variable naming the model for the bare ``onnx`` spec.
MODEL_ENV_VAR = "ARCLOUD_MODEL"

DetectorFactory = Callable[..., Detector]

#: Spec prefix -> factory(argument: str, **options) -> Detector. Extend with ``register_detector``.
DETECTOR_FACTORIES: dict[str, DetectorFactory] = {}


def register_detector(prefix: str, factory: DetectorFactory, *, replace: bool = False) -> None:
    """Make ``make_detector("PREFIX[:ARGUMENT]", **options)`` call ``factory(ARGUMENT, **options)``."""
    if not prefix or not prefix.replace("-", "").replace("_", "").isalnum():
        raise InvalidInput("prefix", "a non-empty name of letters, digits, '-' or '_'", repr(prefix))
    if prefix in DETECTOR_FACTORIES and not replace and DETECTOR_FACTORIES[prefix] is not factory:
        raise InvalidInput("prefix", "a prefix not registered yet (or replace=True)", repr(prefix))
    DETECTOR_FACTORIES[prefix] = factory


def make_detector(spec: str, **options: Any) -> Detector:
    """The detector a spec names, built with ``options`` (e.g. score_threshold, intra_op_threads)."""
    if not isinstance(spec, str) or not spec.strip():
        raise InvalidInput("detector spec", f"PREFIX[:ARGUMENT] with PREFIX one of {_known()}", repr(spec))
    prefix, _, argument = spec.strip().partition(":")
    factory = DETECTOR_FACTORIES.get(prefix)
    if factory is None:
        raise InvalidInput("detector spec", f"PREFIX[:ARGUMENT] with PREFIX one of {_known()}", repr(spec))
    return factory(argument, **options)


def _known() -> str:
    return ", ".join(sorted(DETECTOR_FACTORIES))


#: Spec prefixes that name a model file.
MODEL_PREFIXES = ("onnx", "maskrcnn")


def split_provider(argument: str) -> tuple[str, str]:
    """``PATH@PROVIDER`` -> (PATH, PROVIDER); a path without a known suffix runs on the CPU."""
    from arcloud.detectors.session import EXECUTION_PROVIDERS

    path, at, provider = argument.rpartition("@")
    if at and provider in EXECUTION_PROVIDERS:
        return path, provider
    return argument, "cpu"


def _model_path(argument: str, prefix: str) -> str:
    from arcloud.detectors.catalogue import DEFAULT_MODEL, cached_path, not_cached

    argument = split_provider(argument)[0]
    path = argument or (os.environ.get(MODEL_ENV_VAR, "") if prefix == "onnx" else "")
    expected = f"{prefix}:PATH to a model file" + (
        f", or {MODEL_ENV_VAR} set to one, or the default model {DEFAULT_MODEL} in the model cache" if prefix == "onnx" else ""
    )
    expected += " (serve and replay also run sim:SEED, the simulator's detector, with no model)"
    if not path and prefix == "onnx":
        if not cached_path().is_file():
            raise InvalidInput("detector spec", expected, not_cached())
        return str(cached_path())
    if not path:
        raise InvalidInput("detector spec", expected, f"{prefix!r} with no path")
    if not os.path.isfile(path):
        raise InvalidInput("detector spec", expected, f"{path!r}, which is not a file")
    return path


def check_model_file(spec: str) -> None:
    """Raise ``InvalidInput`` when ``spec`` names a model file (``onnx``, ``maskrcnn``) that is not there;
    loads nothing. A service checks this before it starts worker processes that would each fail."""
    prefix, _, argument = spec.strip().partition(":")
    if prefix in MODEL_PREFIXES:
        _model_path(argument, prefix)


def _onnx_detector(argument: str, **options: Any) -> Detector:
    from arcloud.detectors.maskrcnn import MaskRCNNDetector, is_maskrcnn_export
    from arcloud.detectors.onnx_yolo import YoloSegDetector
    from arcloud.detectors.session import load_session

    path, provider = _model_path(argument, "onnx"), split_provider(argument)[1]
    options.setdefault("execution_provider", provider)
    session = load_session(
        path, intra_op_threads=options.get("intra_op_threads"), execution_provider=options["execution_provider"]
    )
    if is_maskrcnn_export([o.name for o in session.get_outputs()]):
        return MaskRCNNDetector(path, **options)
    return YoloSegDetector(path, **options)


def _maskrcnn_detector(argument: str, **options: Any) -> Detector:
    from arcloud.detectors.maskrcnn import MaskRCNNDetector

    options.setdefault("execution_provider", split_provider(argument)[1])
    return MaskRCNNDetector(_model_path(argument, "maskrcnn"), **options)


register_detector("onnx", _onnx_detector)
register_detector("maskrcnn", _maskrcnn_detector)
