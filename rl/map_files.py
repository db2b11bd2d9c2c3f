"""The grid world of a map, on disk: ``grid.json`` (the map format of rl/maps) and ``grid.png`` (issue 6).

Built from a ``run`` output or a state directory: ``trajectory.tum``, ``cloud.npy`` (sparse map points)
and ``objects.json``.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np

from graph.trajectory import Trajectory
from rl.gridmap import GridMap, MapError
from rl.map_to_grid import build_grid
from rl.vision import renderer_for

log = logging.getLogger(__name__)
GRID_FILE, GRID_PNG, CLOUD_FILE = "grid.json", "grid.png", "cloud.npy"


def grid_for_map(
    name: str,
    trajectory: Trajectory,
    cloud: np.ndarray,
    objects: list[dict],
    cell_m: float = 0.25,
    min_gap_s: float = 5.0,
) -> GridMap:
    """SPEC 6.9's translation of a map into a grid world (see rl.map_to_grid)."""
    objs = [(o["label"], np.asarray(o["mean"], float)) for o in objects]
    return build_grid(
        name,
        trajectory.poses,
        trajectory.timestamps,
        np.asarray(cloud, float),
        objs,
        cell_m=cell_m,
        min_gap_s=min_gap_s,
    )


def write_grid(out: Path, grid: GridMap) -> None:
    """``grid.json`` and a picture of it, ``grid.png`` (walls white, objects coloured, locations numbered)."""
    grid.save(out / GRID_FILE)
    cv2.imwrite(str(out / GRID_PNG), cv2.cvtColor(renderer_for(grid).full_view(), cv2.COLOR_RGB2BGR))


def try_write_grid(out: Path, name: str, trajectory: Trajectory, cloud: np.ndarray, objects: list[dict]) -> bool:
    """Write the grid world of a run's map when it has one (the trajectory must cross itself)."""
    try:
        write_grid(out, grid_for_map(name, trajectory, cloud, objects))
        return True
    except MapError as exc:
        log.info("no grid world for this map: %s", exc)
        return False


def load_map_dir(path: Path, **grid_options) -> GridMap:
    """The grid world of a run output or state directory (``grid_options``: those of ``grid_for_map``)."""
    from sources.tum import read_trajectory

    missing = [f for f in ("trajectory.tum", CLOUD_FILE, "objects.json") if not (path / f).is_file()]
    if missing:
        raise MapError(f"{path} is not a run output or state directory (missing {', '.join(missing)})")
    trajectory = read_trajectory(path / "trajectory.tum")
    cloud = np.load(path / CLOUD_FILE)
    objects = json.loads((path / "objects.json").read_text())
    return grid_for_map(path.resolve().name, trajectory, cloud, objects, **grid_options)
