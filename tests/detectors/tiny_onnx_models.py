"""Tiny ONNX models built with onnx.helper, whose outputs are known, for the detector adapters' tests.

The frame of these tests is 96 x 128 (H x W) with a bright rectangle at columns [32, 96), rows
[24, 72) (``BRIGHT_BOX_PX``) on a dark background; the models' masks follow the image brightness.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 17
FRAME_SHAPE = (96, 128)
BRIGHT_BOX_PX = (32, 24, 96, 72)  # x1, y1, x2, y2 (exclusive ends)
YOLO_SIZE_PX = 64  # frame scale 0.5, resized 64 x 48, 8 px padding top and bottom
YOLO_NAMES = {0: "chair", 1: "dining table", 2: "person"}


def bright_box_image() -> np.ndarray:
    """(96, 128, 3) uint8: 255 inside ``BRIGHT_BOX_PX``, 20 elsewhere."""
    rgb = np.full((*FRAME_SHAPE, 3), 20, dtype=np.uint8)
    x1, y1, x2, y2 = BRIGHT_BOX_PX
    rgb[y1:y2, x1:x2] = 255
    return rgb


def bright_box_mask() -> np.ndarray:
    mask = np.zeros(FRAME_SHAPE, dtype=bool)
    x1, y1, x2, y2 = BRIGHT_BOX_PX
    mask[y1:y2, x1:x2] = True
    return mask


def _save(graph: onnx.GraphProto, path: Path, metadata: dict[str, str] | None = None) -> Path:
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = 8
    for key, value in (metadata or {}).items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def _constant(name: str, array: np.ndarray) -> onnx.NodeProto:
    return helper.make_node("Constant", [], [name], value=numpy_helper.from_array(array, name + "_value"))


def yolo_output0() -> np.ndarray:
    """(1, 4 + 3 + 2, 4) float32: four anchors over the 64 px input, classes (chair, dining table,
    person), mask coefficients (brightness, zero).

    0: chair 0.9 on the bright box (input px: x [16, 48), y [20, 44)); 1: chair 0.8, the same box
    shifted 2 px (NMS drops it); 2: person 0.7 elsewhere; 3: dining table 0.1 (under the threshold)."""
    anchors = np.array(
        [
            # cx, cy, w, h, chair, table, person, coeff brightness, coeff zero
            [32, 32, 32, 24, 0.9, 0.05, 0.0, 1.0, 0.0],
            [34, 32, 32, 24, 0.8, 0.0, 0.0, 1.0, 0.0],
            [10, 52, 12, 16, 0.0, 0.0, 0.7, 1.0, 0.0],
            [32, 32, 40, 30, 0.0, 0.1, 0.0, 1.0, 0.0],
        ],
        dtype=np.float32,
    )
    return anchors.T[None].copy()


def build_tiny_yolo(path: Path, *, size_px: int = YOLO_SIZE_PX, with_names: bool = True) -> Path:
    """A YOLO-seg signature: images [1,3,S,S] -> output0 (constant, ``yolo_output0``), output1
    [1,2,S/4,S/4] whose prototype 0 is the logit 20 * (brightness - 0.5) of each 4x4 cell."""
    proto = size_px // 4
    nodes = [
        _constant("output0", yolo_output0()),
        helper.make_node("ReduceMean", ["images"], ["gray"], axes=[1], keepdims=1),
        helper.make_node("AveragePool", ["gray"], ["cells"], kernel_shape=[4, 4], strides=[4, 4]),
        _constant("half", np.array(0.5, np.float32)),
        _constant("gain", np.array(20.0, np.float32)),
        helper.make_node("Sub", ["cells", "half"], ["centred"]),
        helper.make_node("Mul", ["centred", "gain"], ["bright_logit"]),
        _constant("zeros", np.zeros((1, 1, proto, proto), np.float32)),
        helper.make_node("Concat", ["bright_logit", "zeros"], ["output1"], axis=1),
    ]
    graph = helper.make_graph(
        nodes,
        "tiny_yolo_seg",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, size_px, size_px])],
        [
            helper.make_tensor_value_info("output0", TensorProto.FLOAT, [1, 9, 4]),
            helper.make_tensor_value_info("output1", TensorProto.FLOAT, [1, 2, proto, proto]),
        ],
    )
    return _save(graph, path, {"names": repr(YOLO_NAMES)} if with_names else None)


#: The tiny Mask R-CNN export's detections: (torchvision label, score, box x1, y1, x2, y2 px).
MASKRCNN_DETECTIONS = [
    (1, 0.95, (0.0, 0.0, 20.0, 30.0)),  # person
    (62, 0.9, BRIGHT_BOX_PX),  # chair
    (67, 0.2, (10.0, 10.0, 120.0, 90.0)),  # dining table, under the default threshold
]


def build_tiny_maskrcnn(path: Path, *, fixed_size_px: tuple[int, int] | None = None) -> Path:
    """A torchvision Mask R-CNN export signature: image [3,H,W] -> boxes, labels, scores (constants,
    ``MASKRCNN_DETECTIONS``) and masks [3,1,H,W] = the image brightness for every detection."""
    n = len(MASKRCNN_DETECTIONS)
    height, width = fixed_size_px or ("height", "width")
    nodes = [
        _constant("boxes", np.array([d[2] for d in MASKRCNN_DETECTIONS], np.float32)),
        _constant("labels", np.array([d[0] for d in MASKRCNN_DETECTIONS], np.int64)),
        _constant("scores", np.array([d[1] for d in MASKRCNN_DETECTIONS], np.float32)),
        _constant("zero_axis", np.array([0], np.int64)),
        helper.make_node("ReduceMean", ["image"], ["gray"], axes=[0], keepdims=1),
        helper.make_node("Unsqueeze", ["gray", "zero_axis"], ["gray4"]),
        helper.make_node("Concat", ["gray4"] * n, ["masks"], axis=0),
    ]
    graph = helper.make_graph(
        nodes,
        "tiny_maskrcnn",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [3, height, width])],
        [
            helper.make_tensor_value_info("boxes", TensorProto.FLOAT, [n, 4]),
            helper.make_tensor_value_info("labels", TensorProto.INT64, [n]),
            helper.make_tensor_value_info("scores", TensorProto.FLOAT, [n]),
            helper.make_tensor_value_info("masks", TensorProto.FLOAT, [n, 1, height, width]),
        ],
    )
    return _save(graph, path)


def build_wrong_input_model(path: Path) -> Path:
    """A model with one input [1, 1, 64, 64] and one output: fits no detector adapter."""
    graph = helper.make_graph(
        [helper.make_node("Relu", ["x"], ["y"])],
        "wrong_inputs",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 1, 64, 64])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 1, 64, 64])],
    )
    return _save(graph, path)
