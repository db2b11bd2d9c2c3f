"""Contact sheet of a run's mapped objects on its colour frames, for checking them by eye against the scene.

Usage: python scripts/objects_contact_sheet.py DATASET RUN_DIR OUT.png [--every 50] [--frames 0,400,...]

Each tile is a colour frame with every object of RUN_DIR/objects.json whose centre projects into it drawn
as a circle with "id:label", projected with the run's own estimated pose (RUN_DIR/trajectory.tum) and the
dataset's colour intrinsics. This is how the account of the real sequence's objects in docs/benchmarks.md
("Objects on the real sequence") was made.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from perception.camera import Intrinsics
from perception.features import transform
from perception.warp import project
from sources import open_dataset
from sources.tum import read_trajectory


def draw_objects(rgb: np.ndarray, world_to_camera: np.ndarray, K: Intrinsics, objects: list[dict]) -> np.ndarray:
    """BGR copy of ``rgb`` with each object centre in front of the camera and inside the image marked."""
    img = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    h, w = img.shape[:2]
    centres = transform(world_to_camera, np.array([obj["mean"] for obj in objects], float).reshape(-1, 3))
    for obj, (u, v), z in zip(objects, *project(centres, K), strict=True):
        if z >= 0.2 and 0 <= u < w and 0 <= v < h:
            cv2.circle(img, (int(u), int(v)), 8, (0, 0, 255), 3)
            cv2.putText(
                img,
                f"{obj['id']}:{obj['label']}",
                (int(u) + 10, int(v)),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.8,
                (0, 255, 255),
                2,
            )
    return img


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--every", type=int, default=50)
    ap.add_argument("--frames", default="", help="frame indices, comma separated (instead of --every)")
    ap.add_argument("--columns", type=int, default=4)
    ap.add_argument("--scale", type=float, default=0.5)
    args = ap.parse_args()
    data = open_dataset(args.dataset)
    objects = json.loads((args.run_dir / "objects.json").read_text())
    trajectory = read_trajectory(args.run_dir / "trajectory.tum")
    times = data.timestamps
    frames = [int(f) for f in args.frames.split(",")] if args.frames else list(range(0, len(data), args.every))
    K = data.camera.color
    tiles = []
    for index in frames:
        frame = data.frame(index)
        pose = trajectory.poses[int(np.argmin(np.abs(trajectory.timestamps - times[index])))]
        img = draw_objects(frame.rgb, np.linalg.inv(pose), K, objects)
        cv2.putText(img, f"frame {index}", (10, 30), cv2.FONT_HERSHEY_SIMPLEX, 1.0, (255, 255, 0), 2)
        tiles.append(cv2.resize(img, None, fx=args.scale, fy=args.scale))
    blank = np.zeros_like(tiles[0])
    tiles += [blank] * (-len(tiles) % args.columns)
    rows = [np.hstack(tiles[i : i + args.columns]) for i in range(0, len(tiles), args.columns)]
    cv2.imwrite(str(args.out), np.vstack(rows), [cv2.IMWRITE_JPEG_QUALITY, 80])
    print(f"{len(frames)} frames, {len(objects)} objects -> {args.out}")


if __name__ == "__main__":
    main()
