"""Session creation (cache, errors) and detector specs (registry, autodetection, ARCLOUD_MODEL)."""

from __future__ import annotations

import pytest

from arcloud.detectors import factory
from arcloud.detectors.factory import MODEL_ENV_VAR, check_model_file, make_detector, register_detector
from arcloud.detectors.maskrcnn import MaskRCNNDetector
from arcloud.detectors.onnx_yolo import YoloSegDetector
from arcloud.detectors.session import load_session
from arcloud.errors import InvalidInput, ModelError

# --- Sessions -----------------------------------------------------------------------------------------


def test_one_session_per_model_and_thread_count(tiny_models) -> None:
    first = load_session(tiny_models["yolo"])
    assert load_session(str(tiny_models["yolo"])) is first
    assert load_session(tiny_models["yolo"], intra_op_threads=1) is not first
    assert load_session(tiny_models["maskrcnn"]) is not first


def test_a_missing_model_file_is_a_model_error(tmp_path) -> None:
    missing = tmp_path / "nowhere.onnx"
    with pytest.raises(ModelError, match=f"expected an ONNX file, got no file at {missing}"):
        YoloSegDetector(missing)


def test_a_file_that_is_not_onnx_is_a_model_error(tmp_path) -> None:
    text = tmp_path / "notes.onnx"
    text.write_text("this is not a protobuf")
    with pytest.raises(ModelError, match="expected a loadable ONNX model, got"):
        YoloSegDetector(text)


def test_a_model_with_wrong_inputs_is_a_model_error_saying_expected_and_got(tiny_models) -> None:
    with pytest.raises(ModelError) as caught:
        YoloSegDetector(tiny_models["wrong_inputs"])
    message = str(caught.value)
    assert "does not fit the YOLO-seg adapter" in message
    assert "expected one input float32 [1, 3, S, S]" in message
    assert "got inputs: x tensor(float)[1,1,64,64]; outputs: y tensor(float)[1,1,64,64]" in message
    with pytest.raises(ModelError, match="does not fit the Mask R-CNN adapter.*got inputs: x tensor"):
        MaskRCNNDetector(tiny_models["wrong_inputs"])


def test_bad_thread_count_is_refused(tiny_models) -> None:
    with pytest.raises(InvalidInput, match="intra_op_threads: expected an int >= 1 or None, got 0"):
        load_session(tiny_models["yolo"], intra_op_threads=0)


# --- Specs --------------------------------------------------------------------------------------------


def test_onnx_spec_autodetects_the_adapter_and_passes_options(tiny_models) -> None:
    yolo = make_detector(f"onnx:{tiny_models['yolo']}", score_threshold=0.4)
    assert isinstance(yolo, YoloSegDetector) and yolo.score_threshold == 0.4
    maskrcnn = make_detector(f"onnx:{tiny_models['maskrcnn']}", intra_op_threads=1)
    assert isinstance(maskrcnn, MaskRCNNDetector)
    assert isinstance(make_detector(f"maskrcnn:{tiny_models['maskrcnn']}"), MaskRCNNDetector)
    with pytest.raises(ModelError, match="does not fit the Mask R-CNN adapter"):
        make_detector(f"maskrcnn:{tiny_models['yolo']}")


def test_bare_onnx_spec_reads_the_model_from_the_environment(tiny_models, monkeypatch, tmp_path) -> None:
    monkeypatch.setenv(MODEL_ENV_VAR, str(tiny_models["maskrcnn"]))
    monkeypatch.setenv("ARCLOUD_MODELS", str(tmp_path))  # an empty model cache
    assert isinstance(make_detector("onnx"), MaskRCNNDetector)
    monkeypatch.delenv(MODEL_ENV_VAR)
    with pytest.raises(
        InvalidInput,
        match="expected onnx:PATH to a model file, or ARCLOUD_MODEL set to one, or the default model .* in the model "
        "cache .*got no file at .*get it with `arcloud models pull",
    ):
        make_detector("onnx")


def test_model_files_are_checked_before_anything_loads(tiny_models, tmp_path, monkeypatch) -> None:
    monkeypatch.delenv(MODEL_ENV_VAR, raising=False)
    monkeypatch.setenv("ARCLOUD_MODELS", str(tmp_path / "cache"))  # an empty model cache
    for spec in (f"onnx:{tiny_models['yolo']}", f"maskrcnn:{tiny_models['maskrcnn']}", "sim:0", "gt-masks:anything"):
        check_model_file(spec)  # no model file to check, or one that is there
    with pytest.raises(
        InvalidInput,
        match="also run sim:SEED, the simulator's detector, with no model.*got no file at .*yolo11n-seg-fp32-640.onnx",
    ):
        check_model_file("onnx")
    with pytest.raises(InvalidInput, match="got 'maskrcnn' with no path"):
        check_model_file("maskrcnn")
    missing = tmp_path / "nowhere.onnx"
    for spec in (f"onnx:{missing}", f"maskrcnn:{missing}"):
        with pytest.raises(InvalidInput, match=f"got '{missing}', which is not a file"):
            check_model_file(spec)
    monkeypatch.setenv(MODEL_ENV_VAR, str(missing))
    with pytest.raises(InvalidInput, match="which is not a file"):
        check_model_file("onnx")


def test_unknown_specs_name_the_valid_ones() -> None:
    expected_got = "detector spec: expected PREFIX\\[:ARGUMENT\\] with PREFIX one of .*maskrcnn, onnx.*got 'yolo:x.onnx'"
    with pytest.raises(InvalidInput, match=expected_got):
        make_detector("yolo:x.onnx")
    with pytest.raises(InvalidInput, match="detector spec"):
        make_detector("")


def test_registered_factories_get_the_argument_and_options(monkeypatch) -> None:
    monkeypatch.setattr(factory, "DETECTOR_FACTORIES", dict(factory.DETECTOR_FACTORIES))
    calls = []

    class Fake:
        def detect(self, frame):
            return []

    def build(argument: str, **options: object) -> Fake:
        calls.append((argument, options))
        return Fake()

    register_detector("fake-replay", build)
    assert isinstance(make_detector("fake-replay:scene0000_00", erode_px=2), Fake)
    assert isinstance(make_detector("fake-replay"), Fake)
    assert calls == [("scene0000_00", {"erode_px": 2}), ("", {})]
    with pytest.raises(InvalidInput, match="a prefix not registered yet"):
        register_detector("fake-replay", lambda argument, **options: Fake())
    with pytest.raises(InvalidInput, match="prefix: expected a non-empty name"):
        register_detector("bad:prefix", build)


# --- Execution providers ------------------------------------------------------------------------------


def test_a_spec_picks_the_execution_provider_after_the_path(tiny_models) -> None:
    from arcloud.detectors.factory import split_provider

    assert split_provider("models/y.onnx@cuda") == ("models/y.onnx", "cuda")
    assert split_provider("models/y.onnx@auto") == ("models/y.onnx", "auto")
    assert split_provider("odd@name.onnx") == ("odd@name.onnx", "cpu")  # not a provider: part of the path
    detector = make_detector(f"onnx:{tiny_models['yolo']}@cpu")
    assert detector._session.get_providers() == ["CPUExecutionProvider"]  # type: ignore[attr-defined]  # the YOLO adapter's session
    check_model_file(f"onnx:{tiny_models['yolo']}@cuda")  # the file is there: the suffix is not part of it


def test_cuda_is_refused_with_the_way_to_get_it_where_onnxruntime_has_none(tiny_models) -> None:
    import onnxruntime as ort

    if "CUDAExecutionProvider" in ort.get_available_providers():
        pytest.skip("this onnxruntime has CUDA: test_the_cuda_provider_runs_where_there_is_a_gpu covers it")
    with pytest.raises(ModelError, match="install onnxruntime-gpu"):
        make_detector(f"onnx:{tiny_models['yolo']}@cuda")
    auto = make_detector(f"onnx:{tiny_models['yolo']}@auto")  # falls back to the CPU
    assert auto._session.get_providers() == ["CPUExecutionProvider"]  # type: ignore[attr-defined]  # the YOLO adapter's session
    with pytest.raises(InvalidInput, match="execution_provider"):
        load_session(tiny_models["yolo"], execution_provider="tpu")


def test_the_cuda_provider_runs_where_there_is_a_gpu(tiny_models) -> None:
    import numpy as np
    import onnxruntime as ort

    if "CUDAExecutionProvider" not in ort.get_available_providers():
        pytest.skip("no CUDAExecutionProvider here (onnxruntime-gpu on a machine with a GPU runs this test)")
    gpu, cpu = make_detector(f"onnx:{tiny_models['yolo']}@cuda"), make_detector(f"onnx:{tiny_models['yolo']}@cpu")
    assert gpu._session.get_providers()[0] == "CUDAExecutionProvider"  # type: ignore[attr-defined]  # the YOLO adapter's session
    rgb = np.random.default_rng(0).integers(0, 256, (240, 320, 3), dtype=np.uint8)
    assert [(d.label, round(d.score, 3)) for d in gpu.detect_image(rgb)] == [
        (d.label, round(d.score, 3)) for d in cpu.detect_image(rgb)
    ]  # type: ignore[attr-defined]  # YOLO adapters
