"""The dataset command of the ``arcloud`` CLI: ``render-scannet`` (``add_render_command``). The evaluation
commands are ``arcloud.accuracy.cli``'s."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def run_render_scannet(args: argparse.Namespace) -> int:
    """``arcloud render-scannet``: render an annotated ScanNet mesh into a ScanNet-layout scene."""
    from arcloud.datasets.render_scannet import render_scannet
    from arcloud.datasets.scannet import load_scannet_scene

    scene = load_scannet_scene(args.mesh_dir, scan2aligned=args.axis_alignment)
    scene_dir = render_scannet(
        scene, Path(args.out), users=args.users, frames_per_user=args.frames, seed=args.seed,
        width=args.width, height=args.height, progress=not args.no_progress, style=args.style,
    )  # fmt: skip
    print(f"wrote {scene_dir}")
    return 0


def add_render_command(subparsers: Any) -> None:
    """Add ``render-scannet`` to an argparse sub-parsers object."""
    from arcloud.argtypes import positive_int

    render = subparsers.add_parser(
        "render-scannet",
        help="render an annotated ScanNet mesh into a ScanNet-layout scene walked by K users",
    )
    render.add_argument("--mesh-dir", required=True, help="the scene folder with the mesh, aggregation, segs (and labels tsv)")
    render.add_argument("--out", required=True, help="output root; the scene is written to OUT/<scene>/")
    render.add_argument("--users", type=positive_int, default=10, help="users walking the room, one after the other (default 10)")
    render.add_argument("--frames", type=positive_int, default=60, help="frames per user (default 60)")
    render.add_argument("--seed", type=int, default=0, help="the walks' seed S: user u walks with S * 1000 + u (default 0)")
    render.add_argument(
        "--style",
        choices=("default", "random", "scan"),  # render_scannet.WALK_STYLES (not imported here: the CLI starts light)
        default="default",
        help="walks: default (every user at 1.5 m, plan_walk's defaults), random (each user's eye height, "
        "speed, coverage, glances and hand-held shake drawn from --seed; recorded in render.json) or scan (the "
        "default path, the camera swinging along the walls as an operator scanning the room)",
    )
    render.add_argument("--width", type=int, default=640)
    render.add_argument("--height", type=int, default=480)
    render.add_argument(
        "--axis-alignment", default=None, help="scan2aligned when the scene's .txt has none (as for eval scannet)"
    )
    render.add_argument("--no-progress", action="store_true", help="no progress bar")
    render.set_defaults(handler=run_render_scannet)
