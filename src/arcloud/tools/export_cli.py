"""``arcloud export``: a map of a running service as a file (``GET /v1/maps/{map}/export``).

    arcloud export --map kitchen --format glb --out kitchen.glb                     # boxes, one glTF node each
    arcloud export --map kitchen --format ply --out kitchen.ply --color class       # voxels as coloured points
    arcloud export --map kitchen --format ply --out kitchen.ply --color rgb         # ... in their mean colours
    arcloud export --map kitchen --format scannet --out pred/ --mesh scene_vh_clean_2.ply   # with per-vertex masks
    arcloud export --url https://arcloud.example --token $TOKEN --map kitchen --format json --out kitchen.json

``--format scannet`` writes the prediction files into the folder ``--out`` (or the zip, when ``--out`` ends
in ``.zip``); with ``--mesh``, masks over that mesh's vertices too (computed here from the objects' voxels).
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import zipfile
from pathlib import Path

from arcloud.argtypes import non_negative_int

FORMATS = ("json", "ply", "glb", "scannet")


def add_export_command(subparsers: argparse._SubParsersAction) -> None:
    export = subparsers.add_parser(
        "export",
        help="write a map of a running service as JSON, PLY, GLB or ScanNet prediction files",
        description="The served (confirmed) objects, or every object with --include-tentative, in the map's world frame.",
    )
    export.add_argument("--url", default="http://127.0.0.1:8000", help="service URL (default http://127.0.0.1:8000)")
    export.add_argument("--token", default=None, help="API key token (default $ARCLOUD_TOKEN): a key that may read the map")
    export.add_argument("--map", dest="map_id", required=True, help="map id")
    export.add_argument("--format", dest="fmt", choices=FORMATS, default="json", help="json, ply, glb or scannet (default json)")
    export.add_argument("--out", type=Path, required=True, help="the file to write (scannet: a folder, or a .zip)")
    export.add_argument("--include-tentative", action="store_true", help="tentative objects too")
    export.add_argument(
        "--color",
        choices=("object", "class", "rgb"),
        default="object",
        help="ply: colour by object, by class or by each voxel's mean RGB (default object)",
    )
    export.add_argument("--voxels", action="store_true", help="json: each object's voxel centres, weights and colours")
    export.add_argument("--mesh", type=Path, help="scannet: the scene's mesh (PLY), for per-vertex masks")
    export.add_argument("--retries", type=non_negative_int, default=5, help="tries again after transport errors (default 5)")
    export.set_defaults(handler=run_export)


def run_export(args: argparse.Namespace) -> int:
    from arcloud.client.http import ArcloudClient
    from arcloud.errors import InvalidInput

    if args.mesh is not None and args.fmt != "scannet":
        raise InvalidInput("--mesh", "--format scannet (masks are ScanNet's)", f"--format {args.fmt}")
    options: dict[str, str | bool] = {"color": args.color}
    if args.include_tentative:
        options["include"] = "tentative"
    with ArcloudClient(args.url, token=args.token, max_retries=args.retries) as client:
        if args.fmt == "scannet" and args.mesh is not None:
            files = scannet_with_masks(client.export(args.map_id, "json", voxels=True, **options), args.map_id, args.mesh)
        elif args.fmt == "scannet":
            with zipfile.ZipFile(io.BytesIO(client.export(args.map_id, "scannet", **options))) as archive:
                files = {name: archive.read(name) for name in archive.namelist()}
        else:
            data = client.export(args.map_id, args.fmt, voxels=args.voxels, **options)
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_bytes(data)
            print(f"wrote {args.out} ({len(data)} bytes)", file=sys.stderr)
            return 0
    write_files(files, args.out)
    print(f"wrote {len(files)} files to {args.out}", file=sys.stderr)
    return 0


def scannet_with_masks(document: bytes, scene: str, mesh: Path) -> dict[str, bytes]:
    """ScanNet files with masks over ``mesh``'s vertices, from a JSON export with voxels."""
    import numpy as np
    import open3d as o3d

    from arcloud.core.voxels import points_to_keys
    from arcloud.errors import InvalidInput
    from arcloud.formats.scannet import Prediction, scannet_files

    vertices = np.asarray(o3d.io.read_triangle_mesh(mesh).vertices)
    if len(vertices) == 0:
        raise InvalidInput("--mesh", "a PLY mesh with vertices", str(mesh))
    predictions, size = [], 0.05
    for obj in json.loads(document)["objects"]:
        if obj["aabb"] is None:
            continue
        size = obj["voxels"]["voxel_size_m"]
        keys = points_to_keys(np.asarray(obj["voxels"]["centers"], np.float64).reshape(-1, 3), size)
        predictions.append(
            Prediction(obj["label"], obj["score"], np.array(obj["aabb"]["min"]), np.array(obj["aabb"]["max"]), keys)
        )
    return scannet_files(scene, predictions, vertices_m=vertices, voxel_size_m=size)


def write_files(files: dict[str, bytes], out: Path) -> None:
    """Into the folder ``out``, or the zip ``out`` when it ends in .zip."""
    if out.suffix == ".zip":
        out.parent.mkdir(parents=True, exist_ok=True)
        with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as archive:
            for name, data in files.items():
                archive.writestr(name, data)
        return
    for name, data in files.items():
        path = out / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
