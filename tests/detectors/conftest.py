"""Fixtures of the detector tests: the tiny ONNX models of ``tiny_onnx_models``, built once per session."""

from __future__ import annotations

from pathlib import Path

import pytest
from tiny_onnx_models import build_tiny_maskrcnn, build_tiny_yolo, build_wrong_input_model


@pytest.fixture(scope="session")
def tiny_models(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Paths of the tiny models, built once per test session."""
    folder = tmp_path_factory.mktemp("tiny_models")
    return {
        "yolo": build_tiny_yolo(folder / "tiny_yolo.onnx"),
        "yolo_no_names": build_tiny_yolo(folder / "tiny_yolo_no_names.onnx", with_names=False),
        "maskrcnn": build_tiny_maskrcnn(folder / "tiny_maskrcnn.onnx"),
        "maskrcnn_fixed": build_tiny_maskrcnn(folder / "tiny_maskrcnn_fixed.onnx", fixed_size_px=(48, 64)),
        "wrong_inputs": build_wrong_input_model(folder / "wrong_inputs.onnx"),
    }
