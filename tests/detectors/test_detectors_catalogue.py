"""The model catalogue and cache (``arcloud models list | pull | verify | path``), through the CLI: pulls from
../shared/models (skipped with a reason when absent), checked by sha256 or, for a user's own export, by
signature; the bare ``onnx`` detector spec runs the default model from the cache or says how to get it."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from arcloud.cli import main as cli_main
from arcloud.detectors.catalogue import CATALOGUE, DEFAULT_MODEL, catalogue_model, models_dir, sha256_of
from arcloud.detectors.factory import make_detector
from arcloud.detectors.onnx_yolo import YoloSegDetector
from arcloud.errors import InvalidInput


@pytest.fixture
def cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """An empty model cache ($ARCLOUD_MODELS), and no $ARCLOUD_MODEL."""
    monkeypatch.setenv("ARCLOUD_MODELS", str(tmp_path / "cache"))
    monkeypatch.delenv("ARCLOUD_MODEL", raising=False)
    return tmp_path / "cache"


def arcloud(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    """(exit status, stdout, stderr) of ``arcloud ARGV``."""
    capsys.readouterr()
    status = cli_main(list(argv))
    out, err = capsys.readouterr()
    return status, out, err


@pytest.mark.shared
def test_the_catalogue_holds_the_shared_models_by_their_sha256(shared: type) -> None:
    table = shared.path("models/README.md").read_text()
    assert DEFAULT_MODEL == "yolo11n-seg-fp32-640" and set(CATALOGUE) >= {DEFAULT_MODEL, "yolov8n-seg-fp32-640"}
    for name, model in CATALOGUE.items():
        (row,) = [line for line in table.splitlines() if line.startswith(f"| `{model.file_name}`")]
        assert model.sha256 in row and f"[1,3,{model.input_size_px},{model.input_size_px}]" in row, name
        assert sha256_of(shared.path(f"models/{model.file_name}")) == model.sha256, name
        assert model.licence == "AGPL-3.0" and model.weights_url.startswith("https://github.com/ultralytics/assets/releases/")
        assert model.export_command == f"yolo export model={model.weights_file} format=onnx imgsz={model.input_size_px}"


@pytest.mark.shared
def test_pull_from_a_folder_checks_the_sha256_and_prints_the_licence(
    shared: type, cache: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = shared.path("models")
    status, out, _ = arcloud(capsys, "models", "pull", "--from", str(folder))  # the default model, found in the folder
    assert status == 0, out
    cached = cache / f"{DEFAULT_MODEL}.onnx"
    assert f"pulled {DEFAULT_MODEL} into {cached}" in out and "checked by the catalogue's sha256" in out
    assert "licence of its weights: AGPL-3.0" in out
    assert cached.read_bytes() == (folder / cached.name).read_bytes()
    status, out, _ = arcloud(capsys, "models", "verify")
    assert status == 0 and out.startswith(f"{cached}: sha256 {catalogue_model().sha256}, the catalogue's sha256"), out
    status, out, _ = arcloud(capsys, "models", "list")
    assert status == 0 and out.startswith(f"model cache: {cache} ($ARCLOUD_MODELS)")
    assert re.search(rf"^{DEFAULT_MODEL}\s+640\s+AGPL-3.0\s+yes\s.*\(default\)$", out, re.M), out
    assert re.search(r"^yolov8n-seg-fp32-640\s+640\s+AGPL-3.0\s+no\s", out, re.M), out
    assert arcloud(capsys, "models", "path")[:2] == (0, f"{cache}\n")
    assert arcloud(capsys, "models", "path", DEFAULT_MODEL)[:2] == (0, f"{cached}\n")
    status, out, err = arcloud(capsys, "models", "path", "yolov8n-seg-fp32-640")
    assert status == 1 and out == f"{cache / 'yolov8n-seg-fp32-640.onnx'}\n"
    assert "`arcloud models pull yolov8n-seg-fp32-640 --from FILE`" in err


@pytest.mark.shared
def test_verify_checks_each_cached_model_and_says_the_default_is_missing(
    shared: type, cache: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A new user's review: with YOLOv8n-seg alone pulled, `models verify` said only that YOLO11n-seg was missing (2)."""
    assert arcloud(capsys, "models", "pull", "yolov8n-seg-fp32-640", "--from", str(shared.path("models")))[0] == 0
    status, out, err = arcloud(capsys, "models", "verify")
    assert (
        status == 0
        and out
        == f"{cache / 'yolov8n-seg-fp32-640.onnx'}: sha256 {catalogue_model('yolov8n-seg-fp32-640').sha256}, the catalogue's sha256\n"
    )
    assert err.startswith(f"arcloud: the default model is not cached (no file at {cache / (DEFAULT_MODEL + '.onnx')}")


@pytest.mark.shared
def test_pull_refuses_other_bytes_unless_an_export_of_the_model(
    shared: type, cache: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    v8, int8 = shared.path("models/yolov8n-seg-fp32-640.onnx"), shared.path("models/yolo11n-seg-int8-640.onnx")
    status, _, err = arcloud(capsys, "models", "pull", DEFAULT_MODEL, "--from", str(v8))
    assert status == 2 and f"expected the sha256 of {DEFAULT_MODEL}, {catalogue_model().sha256}, got {sha256_of(v8)}" in err
    assert "give --exported to check its signature instead" in err
    status, _, err = arcloud(capsys, "models", "pull", DEFAULT_MODEL, "--from", str(v8), "--exported")
    assert status == 2 and "expected an export of YOLO11n-seg" in err and "YOLOv8n-seg" in err, err
    assert not cache.exists() or not any(cache.iterdir())  # nothing written by a refused pull

    # A quantized export has the same inputs and outputs, and is not the float32 model the catalogue names
    status, _, err = arcloud(capsys, "models", "pull", DEFAULT_MODEL, "--from", str(int8), "--exported")
    assert status == 2 and "expected a float32 export for yolo11n-seg-fp32-640, got a quantized one" in err, err
    # Another build of the same weights (here: written again with another producer) passes on its signature; verify
    # then holds it to its bytes.
    import onnx

    rebuilt = onnx.load(str(shared.path(f"models/{DEFAULT_MODEL}.onnx")))
    rebuilt.producer_version = "another build"
    onnx.save(rebuilt, str(cache.parent / "yolo11n-seg.onnx"))
    status, out, _ = arcloud(
        capsys, "models", "pull", DEFAULT_MODEL, "--from", str(cache.parent / "yolo11n-seg.onnx"), "--exported"
    )
    assert status == 0 and "checked by its signature: YOLO11n-seg, input 640 x 640, the 80 COCO classes" in out, out
    status, out, _ = arcloud(capsys, "models", "verify", DEFAULT_MODEL)
    assert status == 0 and "the sha256 recorded when it was pulled" in out
    with open(cache / f"{DEFAULT_MODEL}.onnx", "ab") as cached:
        cached.write(b"\0")
    status, _, err = arcloud(capsys, "models", "verify")
    assert status == 2 and "(recorded at its pull), got" in err and "it changed since it was pulled" in err, err


def test_pull_refuses_a_yolo_seg_of_another_size_and_what_is_not_a_model(
    tiny_models: dict[str, Path], cache: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    status, _, err = arcloud(capsys, "models", "pull", "--from", str(tiny_models["yolo"]), "--exported")
    assert status == 2 and "expected an input of 640 x 640 for yolo11n-seg-fp32-640, got" in err, err
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    assert arcloud(capsys, "models", "pull", "--from", str(junk), "--exported")[0] == 2
    status, _, err = arcloud(capsys, "models", "pull", "--from", str(tmp_path / "nothing"))
    assert status == 2 and "expected a model file or a folder, got nothing there" in err
    status, _, err = arcloud(capsys, "models", "pull", "--from", str(tmp_path))
    assert status == 2 and "holding yolo11n-seg-fp32-640.onnx or yolo11n-seg.onnx, got neither" in err
    status, _, err = arcloud(capsys, "models", "pull", "yolo99", "--from", str(junk))
    assert (
        status == 2
        and "model: expected a model of the catalogue (yolo11n-seg-fp32-640, yolov8n-seg-fp32-640), got 'yolo99'" in err
    )
    assert not cache.exists() or not any(cache.iterdir())


def test_pull_without_a_file_says_how_to_export_it(cache: Path, capsys: pytest.CaptureFixture[str]) -> None:
    status, out, err = arcloud(capsys, "models", "pull", "yolov8n-seg-fp32-640")
    assert status == 1 and out == ""
    assert "https://github.com/ultralytics/assets/releases/download/v8.2.0/yolov8n-seg.pt (AGPL-3.0)" in err
    assert "  yolo export model=yolov8n-seg.pt format=onnx imgsz=640\n" in err
    assert "  arcloud models pull yolov8n-seg-fp32-640 --from yolov8n-seg.onnx --exported\n" in err
    assert not cache.exists()
    status, _, err = arcloud(capsys, "models", "verify")
    assert status == 2 and f"`arcloud models pull {DEFAULT_MODEL} --from FILE`" in err


@pytest.mark.shared
def test_the_bare_onnx_spec_runs_the_default_model_from_the_cache(
    shared: type, cache: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(InvalidInput) as missing:
        make_detector("onnx")
    assert f"got no file at {cache / DEFAULT_MODEL}.onnx" in str(missing.value)
    assert f"get it with `arcloud models pull {DEFAULT_MODEL} --from FILE`" in str(missing.value)
    assert arcloud(capsys, "models", "pull", "--from", str(shared.path("models")))[0] == 0
    detector = make_detector("onnx", intra_op_threads=1)
    assert isinstance(detector, YoloSegDetector) and detector.model_path == str(cache / f"{DEFAULT_MODEL}.onnx")
    other = shared.path("models/yolov8n-seg-fp32-640.onnx")
    monkeypatch.setenv("ARCLOUD_MODEL", str(other))  # still first
    detector = make_detector("onnx", intra_op_threads=1)
    assert isinstance(detector, YoloSegDetector) and detector.model_path == str(other)


def test_the_cache_is_arcloud_models_else_the_users_cache_folder(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ARCLOUD_MODELS", "/srv/models")
    assert models_dir() == Path("/srv/models")
    monkeypatch.delenv("ARCLOUD_MODELS")
    monkeypatch.setenv("XDG_CACHE_HOME", "/var/cache/me")
    assert models_dir() == Path("/var/cache/me/arcloud/models")
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", "/home/me")
    assert models_dir() == Path("/home/me/.cache/arcloud/models")
