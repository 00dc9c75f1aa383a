"""``arcloud models list | pull | verify | path``: the detector models a user can get, and the model cache
(``arcloud.detectors.catalogue``). Nothing is downloaded: ``pull`` takes a file the user has (``--from``)
and, without one, says how to export it.

    arcloud models list
    arcloud models pull yolo11n-seg-fp32-640                                  # how to get the file
    yolo export model=yolo11n-seg.pt format=onnx imgsz=640                    # pip install ultralytics
    arcloud models pull yolo11n-seg-fp32-640 --from yolo11n-seg.onnx --exported
    arcloud models verify
    arcloud serve --detector onnx:$(arcloud models path yolov8n-seg-fp32-640)
"""

from __future__ import annotations

import argparse
import sys

NAME_HELP = "a model of `arcloud models list` (default: the default model)"


def add_models_commands(subparsers: argparse._SubParsersAction) -> None:
    models = subparsers.add_parser(
        "models",
        help="the detector models a user can get, and the model cache ($ARCLOUD_MODELS)",
        description="The catalogue of known detector models and the cache they are kept in ($ARCLOUD_MODELS, else "
        "~/.cache/arcloud/models). `serve` and `worker` without --detector run the default model from the cache.",
    )
    actions = models.add_subparsers(dest="action", required=True)
    listing = actions.add_parser("list", help="the catalogue: names, input sizes, licences, what the cache holds")
    listing.set_defaults(handler=run_list)
    pull = actions.add_parser(
        "pull",
        help="put a model's ONNX file into the cache, checked (without --from: how to get the file)",
        description="Copies FILE (or DIR/NAME.onnx, or the export's file in DIR) into the cache when its sha256 is the "
        "catalogue's, or with --exported when it is a YOLO-seg export of the model's input size and the COCO classes. "
        "Nothing is downloaded.",
    )
    pull.add_argument("name", nargs="?", metavar="NAME", help=NAME_HELP)
    pull.add_argument("--from", dest="source", metavar="FILE|DIR", help="the ONNX file, or a folder holding it")
    pull.add_argument(
        "--exported",
        action="store_true",
        help="a file you exported yourself (its bytes differ from build to build): check its signature, not its sha256",
    )
    pull.set_defaults(handler=run_pull)
    verify = actions.add_parser("verify", help="check that a cached model (without NAME: each) is what was pulled (its sha256)")
    verify.add_argument("name", nargs="?", metavar="NAME", help=NAME_HELP)
    verify.set_defaults(handler=run_verify)
    path = actions.add_parser("path", help="print the cache folder, or a model's file in it (exit 1 when not pulled)")
    path.add_argument("name", nargs="?", metavar="NAME", help="a model of `arcloud models list` (default: the folder)")
    path.set_defaults(handler=run_path)


def run_list(args: argparse.Namespace) -> int:
    from arcloud.detectors.catalogue import CATALOGUE, DEFAULT_MODEL, MODELS_ENV_VAR, cached_path, models_dir

    print(f"model cache: {models_dir()} (${MODELS_ENV_VAR})")
    print(f"{'NAME':<22}  {'INPUT':>5}  {'LICENCE':<8}  {'CACHED':<6}  WHAT")
    for name, model in CATALOGUE.items():
        default = " (default)" if name == DEFAULT_MODEL else ""
        cached = "yes" if cached_path(name).is_file() else "no"
        print(f"{name:<22}  {model.input_size_px:>5}  {model.licence:<8}  {cached:<6}  {model.summary}{default}")
    return 0


def run_pull(args: argparse.Namespace) -> int:
    from arcloud.detectors.catalogue import LICENCE_URL, catalogue_model, pull

    model = catalogue_model(args.name)
    if args.source is None:
        print(
            f"{model.name}: no ONNX file of it is published to download; its weights are {model.weights_url} "
            f"({model.licence}). Export the ONNX file with the ultralytics package (it downloads the weights), then pull it:\n"
            f"  pip install ultralytics\n"
            f"  {model.export_command}\n"
            f"  {model.pull_command(model.exported_file)} --exported\n"
            f"A file of the catalogue's exact bytes (sha256 {model.sha256}) needs no --exported.",
            file=sys.stderr,
        )
        return 1
    checked = pull(model.name, args.source, exported=args.exported)
    print(f"pulled {model.name} into {checked.path} (sha256 {checked.sha256}; checked by {checked.how})")
    print(f"licence of its weights: {model.licence} (Ultralytics, {LICENCE_URL}): read it before you serve the model to others")
    return 0


def run_verify(args: argparse.Namespace) -> int:
    """The model named, else every model of the catalogue in the cache (the default's absence said, not an error when
    another is there: a new user who pulled YOLOv8n-seg alone was told only that YOLO11n-seg was missing)."""
    from arcloud.detectors.catalogue import CATALOGUE, DEFAULT_MODEL, cached_path, catalogue_model, not_cached, verify

    names = [catalogue_model(args.name).name] if args.name else [n for n in CATALOGUE if cached_path(n).is_file()]
    for name in names or [DEFAULT_MODEL]:  # none cached: verify says the default is missing
        checked = verify(name)
        print(f"{checked.path}: sha256 {checked.sha256}, {checked.how}")
    if not args.name and DEFAULT_MODEL not in names:
        print(f"arcloud: the default model is not cached ({not_cached(DEFAULT_MODEL)}); `serve` runs it unless --detector "
              "names another", file=sys.stderr)  # fmt: skip
    return 0


def run_path(args: argparse.Namespace) -> int:
    from arcloud.detectors.catalogue import cached_path, models_dir, not_cached

    if args.name is None:
        print(models_dir())
        return 0
    path = cached_path(args.name)
    print(path)
    if not path.is_file():
        print(f"arcloud: {not_cached(args.name)}", file=sys.stderr)
        return 1
    return 0
