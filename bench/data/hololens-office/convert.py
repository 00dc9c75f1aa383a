"""Make this folder's frames from DeepVideoMVS's HoloLens sample scene, in the 7-Scenes layout ``arcloud eval`` reads.

The source is ``sample-data/hololens-dataset/000`` of https://github.com/ardaduz/deep-video-mvs (MIT licence, commit
fa14288f): ``images/NNNNN.png`` (540x360 colour), ``depth/NNNNN.png`` (uint16 millimetres, 0 = invalid, registered to
the colour), ``poses.txt`` (a row-major camera-to-world 4x4 a line, OpenCV axes, in the files' order) and ``K.txt``
(3x3). Written here: ``frame-0NNNNN.color.jpg`` (JPEG quality 90: the source's PNGs are 100 MB), ``.depth.png``
(the same millimetres, PNG at its strongest compression), ``.pose.txt`` and ``camera-intrinsics.txt``; the frame
numbers are the source's. About 39 MB in all.

    .venv/bin/python bench/data/hololens-office/convert.py SOURCE_DIR [--out bench/data/hololens-office]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

JPEG_QUALITY = 90


def convert(source: Path, out: Path) -> int:
    """Write the frames of ``source`` into ``out``; returns how many."""
    colour_files = sorted((source / "images").glob("*.png"))
    poses = np.loadtxt(source / "poses.txt").reshape(-1, 4, 4)
    if len(colour_files) != len(poses):
        raise SystemExit(f"{source}: expected a pose per image, got {len(poses)} poses for {len(colour_files)} images")
    out.mkdir(parents=True, exist_ok=True)
    np.savetxt(out / "camera-intrinsics.txt", np.loadtxt(source / "K.txt").reshape(3, 3), fmt="%.6f")
    for path, pose in zip(colour_files, poses, strict=True):
        stem = f"frame-{int(path.stem):06d}"
        depth = cv2.imread(str(source / "depth" / path.name), cv2.IMREAD_UNCHANGED)
        if depth is None or depth.dtype != np.uint16:
            raise SystemExit(f"{source / 'depth' / path.name}: expected a uint16 PNG")
        colour = cv2.imread(str(path), cv2.IMREAD_COLOR)
        cv2.imwrite(str(out / f"{stem}.color.jpg"), colour, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        cv2.imwrite(str(out / f"{stem}.depth.png"), depth, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        np.savetxt(out / f"{stem}.pose.txt", pose, fmt="%.9f")
    return len(colour_files)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", type=Path, help="the scene folder: images/, depth/, poses.txt, K.txt")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent)
    args = parser.parse_args()
    print(f"wrote {convert(args.source, args.out)} frames to {args.out}")


if __name__ == "__main__":
    main()
