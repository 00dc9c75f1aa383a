"""The detector models a user can get (the catalogue) and the folder they are kept in (the model cache).

    arcloud models list                                   # the catalogue, the default, what the cache holds
    arcloud models pull NAME --from FILE|DIR [--exported] # FILE (or DIR/NAME.onnx) into the cache, checked
    arcloud models verify [NAME]                          # the cached file is still what was pulled
    arcloud models path [NAME]                            # the cache folder, or a model's file in it

Where the files come from: the weights are Ultralytics' YOLO-seg (COCO), published as PyTorch files
(``weights_url``) under AGPL-3.0. No ONNX file of them is published whose bytes could be checked, so arcloud
downloads nothing: the user exports one with the ``ultralytics`` package (``export_command``) and pulls it
with ``--exported`` (its bytes differ from build to build, so its signature is checked: one input of the
catalogue's size, YOLO-seg outputs, the 80 COCO classes), or pulls a file of the catalogue's exact bytes
(``sha256``: the files this project measured its figures with), checked by its hash. A pull records the hash
of what it took (``NAME.onnx.sha256`` beside it), so that ``verify`` tells a file changed since.

The cache is ``$ARCLOUD_MODELS``, else ``$XDG_CACHE_HOME/arcloud/models``, else ``~/.cache/arcloud/models``.
The bare detector spec ``onnx`` (no path, no ``$ARCLOUD_MODEL``) runs ``DEFAULT_MODEL`` from it.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

from arcloud.errors import InvalidInput, ModelError

#: The environment variable naming the model cache.
MODELS_ENV_VAR = "ARCLOUD_MODELS"
LICENCE_URL = "https://github.com/ultralytics/ultralytics/blob/main/LICENSE"


@dataclass(frozen=True, slots=True)
class CatalogueModel:
    """A model of the catalogue: ``name`` (its file in the cache is ``NAME.onnx``), the ``architecture`` its
    Ultralytics export names in its metadata, the ``sha256`` of the reference ONNX file, its square input size,
    where its weights are published and how to export them."""

    name: str
    architecture: str
    summary: str
    sha256: str
    input_size_px: int
    weights_url: str
    licence: str = "AGPL-3.0"

    @property
    def file_name(self) -> str:
        return f"{self.name}.onnx"

    @property
    def weights_file(self) -> str:
        return self.weights_url.rsplit("/", 1)[1]

    @property
    def exported_file(self) -> str:
        """The file ``export_command`` writes (beside the weights)."""
        return self.weights_file.removesuffix(".pt") + ".onnx"

    @property
    def export_command(self) -> str:
        """Exports the ONNX file from the published weights (``pip install ultralytics``; it downloads them)."""
        return f"yolo export model={self.weights_file} format=onnx imgsz={self.input_size_px}"

    def pull_command(self, source: str = "FILE") -> str:
        return f"arcloud models pull {self.name} --from {source}"


CATALOGUE: dict[str, CatalogueModel] = {
    model.name: model
    for model in (
        CatalogueModel(
            "yolo11n-seg-fp32-640",
            "YOLO11n-seg",
            "Ultralytics YOLO11n-seg, COCO, float32, 640 x 640 (COCO mAP box 38.9 / mask 32.0)",
            "9cc40615d8a1862baebeae1eb92b3ce4fad6daf2f4fd770921f8fc7a075afb6f",
            640,
            "https://github.com/ultralytics/assets/releases/download/v8.3.0/yolo11n-seg.pt",
        ),
        CatalogueModel(
            "yolov8n-seg-fp32-640",
            "YOLOv8n-seg",
            "Ultralytics YOLOv8n-seg, COCO, float32, 640 x 640 (COCO mAP box 36.7 / mask 30.5)",
            "326d9b0e9a593dc6689de9ee0bd72dd5e6713005fb5d738e0726fdd7777bf768",
            640,
            "https://github.com/ultralytics/assets/releases/download/v8.2.0/yolov8n-seg.pt",
        ),
    )
}
#: The model the bare ``onnx`` spec runs (``serve`` and ``worker`` without ``--detector``).
DEFAULT_MODEL = "yolo11n-seg-fp32-640"


def catalogue_model(name: str | None = None) -> CatalogueModel:
    """The catalogue's model of this name (None: the default); ``InvalidInput`` naming the known ones."""
    model = CATALOGUE.get(DEFAULT_MODEL if name is None else name)
    if model is None:
        raise InvalidInput("model", f"a model of the catalogue ({', '.join(CATALOGUE)})", repr(name))
    return model


def models_dir() -> Path:
    """The model cache: ``$ARCLOUD_MODELS``, else ``$XDG_CACHE_HOME/arcloud/models``, else ``~/.cache/arcloud/models``."""
    if os.environ.get(MODELS_ENV_VAR):
        return Path(os.environ[MODELS_ENV_VAR])
    cache = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(cache) / "arcloud" / "models"


def cached_path(name: str | None = None) -> Path:
    """Where the cache keeps the model (whether it is there or not)."""
    return models_dir() / catalogue_model(name).file_name


def not_cached(name: str | None = None) -> str:
    """What to say when the model is not in the cache: where it was looked for, and the command that gets it."""
    model = catalogue_model(name)
    return (
        f"no file at {cached_path(name)} (model {model.name} is not in the model cache, ${MODELS_ENV_VAR}): get it with "
        f"`{model.pull_command()}` (`arcloud models pull {model.name}` says how to make FILE)"
    )


def sha256_of(path: str | os.PathLike[str]) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


@dataclass(frozen=True, slots=True)
class Checked:
    """A model file checked: ``path``, its ``sha256``, and ``how`` ("the catalogue's sha256", ...)."""

    path: Path
    sha256: str
    how: str


def pull(name: str | None, source: str | os.PathLike[str], *, exported: bool = False) -> Checked:
    """Copy a model file into the cache, checked: ``source`` is the file, or a folder holding ``NAME.onnx`` or the
    export's file (``yolo11n-seg.onnx``). Its sha256 must be the catalogue's, or with ``exported`` (a file the user
    exported: its bytes are their build's) its signature the model's. ``ModelError`` otherwise; nothing is written."""
    model = catalogue_model(name)
    path = _source_file(model, Path(source))
    digest = sha256_of(path)
    if digest == model.sha256:
        how = "the catalogue's sha256"
    elif exported:
        check_signature(model, path)
        how = f"its signature: {model.architecture}, input {model.input_size_px} x {model.input_size_px}, the 80 COCO classes"
    else:
        raise ModelError(
            f"{path}: expected the sha256 of {model.name}, {model.sha256}, got {digest}; a file exported with "
            f"`{model.export_command}` differs from build to build: give --exported to check its signature instead"
        )
    target = cached_path(model.name)
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=target.parent, prefix=f".{model.name}-", delete=False) as partial:
        try:
            with open(path, "rb") as file:
                shutil.copyfileobj(file, partial)
            partial.close()
            if sha256_of(partial.name) != digest:
                raise ModelError(f"{path}: changed while it was copied into the model cache; pull it again")
            os.chmod(partial.name, 0o644)
            os.replace(partial.name, target)  # whole or not at all: a reader never sees half a file
        except BaseException:
            Path(partial.name).unlink(missing_ok=True)
            raise
    _record_path(target).write_text(f"{digest}  {target.name}\n")
    return Checked(target, digest, how)


def verify(name: str | None = None) -> Checked:
    """The cached model, checked: its sha256 is the catalogue's, or the one its pull recorded (an export of the
    user's). ``ModelError`` saying what was expected and what is there otherwise."""
    model = catalogue_model(name)
    path = cached_path(model.name)
    if not path.is_file():
        raise ModelError(not_cached(model.name))
    digest = sha256_of(path)
    if digest == model.sha256:
        return Checked(path, digest, "the catalogue's sha256")
    record = _record_path(path)
    recorded = record.read_text().split()[0] if record.is_file() and record.read_text().strip() else None
    if digest == recorded:
        return Checked(path, digest, f"the sha256 recorded when it was pulled (an export of yours; {record.name})")
    expected = f"{model.sha256} (the catalogue's)" + (f" or {recorded} (recorded at its pull)" if recorded else "")
    raise ModelError(
        f"{path}: expected the sha256 {expected}, got {digest}: it changed since it was pulled; pull it again "
        f"(`{model.pull_command()}`)"
    )


#: Operators only a quantized export holds (their names are plain strings in the file): the catalogue's models
#: are all float32, and an int8 file has the same inputs and outputs.
QUANTIZED_OPERATORS = (b"QuantizeLinear", b"ConvInteger", b"MatMulInteger", b"QLinearConv", b"QLinearMatMul")


def check_signature(model: CatalogueModel, path: Path) -> None:
    """``ModelError`` unless the file is a float32 YOLO-seg ONNX model of the model's input size and the 80 COCO
    classes, and, when its metadata has an Ultralytics ``description``, of the model's architecture (loads it in
    onnxruntime)."""
    from arcloud.detectors.coco import COCO80
    from arcloud.detectors.onnx_yolo import YoloSegDetector
    from arcloud.detectors.session import load_session, metadata

    content = path.read_bytes()
    quantized = [op.decode() for op in QUANTIZED_OPERATORS if op in content]
    if quantized:
        raise ModelError(f"{path}: expected a float32 export for {model.name}, got a quantized one ({', '.join(quantized)})")
    detector = YoloSegDetector(path, intra_op_threads=1)
    description = metadata(load_session(path, intra_op_threads=1)).get("description", "")
    if description.startswith("Ultralytics ") and not description.startswith(f"Ultralytics {model.architecture} "):
        raise ModelError(f"{path}: expected an export of {model.architecture} for {model.name}, got {description[:60]!r}")
    size = model.input_size_px
    if detector.input_size_px != size:
        raise ModelError(f"{path}: expected an input of {size} x {size} for {model.name}, got {detector.input_size_px}")
    if detector.class_names != COCO80:
        raise ModelError(f"{path}: expected the 80 COCO classes of {model.name}, got {len(detector.class_names)} classes")


def _source_file(model: CatalogueModel, source: Path) -> Path:
    if source.is_dir():
        for name in (model.file_name, model.exported_file):
            if (source / name).is_file():
                return source / name
        raise ModelError(
            f"--from {source}: expected a file, or a folder holding {model.file_name} or {model.exported_file}, got neither"
        )
    if not source.is_file():
        raise ModelError(f"--from {source}: expected a model file or a folder, got nothing there")
    return source


def _record_path(path: Path) -> Path:
    return path.with_name(path.name + ".sha256")


__all__ = [
    "CATALOGUE",
    "DEFAULT_MODEL",
    "MODELS_ENV_VAR",
    "CatalogueModel",
    "Checked",
    "cached_path",
    "catalogue_model",
    "check_signature",
    "models_dir",
    "not_cached",
    "pull",
    "sha256_of",
    "verify",
]
