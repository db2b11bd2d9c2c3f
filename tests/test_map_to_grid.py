"""Map -> grid world: ground plane, walls from map points, objects as feature blocks, crossings (issue 6)."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import pytest

from rl.gridmap import GridMap, MapError
from rl.map_to_grid import GroundFrame, build_grid, crossing_cells, ground_frame


def upright_pose(position, yaw: float) -> np.ndarray:
    """Camera-to-world pose, OpenCV camera axes, world z up, looking horizontally along ``yaw``."""
    forward = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    right = np.cross(down, forward)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, forward], axis=1)
    T[:3, 3] = position
    return T


def square_laps(laps: int = 2, side: float = 2.0, step: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    corners = np.array([[0, 0], [side, 0], [side, side], [0, side], [0, 0]], float)
    poses = []
    for _ in range(laps):
        for a, b in pairwise(corners):
            yaw = np.arctan2(*(b - a)[::-1])
            for s in np.arange(0, 1, step / side):
                poses.append(upright_pose([*(a + s * (b - a)), 1.2], yaw))
    return np.stack(poses), np.arange(len(poses)) * 0.2  # 5 Hz


def wall_points(x: float, y0: float, y1: float) -> np.ndarray:
    y, z = np.meshgrid(np.linspace(y0, y1, 60), np.linspace(0.0, 2.0, 30))
    return np.stack([np.full(y.size, x), y.ravel(), z.ravel()], axis=1)


def floor_points() -> np.ndarray:
    x, y = np.meshgrid(np.linspace(-1, 3, 40), np.linspace(-1, 3, 40))
    return np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)


def test_ground_frame_finds_up_from_upright_cameras_and_the_floor():
    poses, _ = square_laps()
    frame = ground_frame(poses, floor_points(), cell_m=0.25)
    assert np.allclose(frame.up, [0, 0, 1], atol=1e-9)
    assert abs(frame.origin @ frame.up) < 1e-6  # floor at z = 0
    assert np.isclose(np.cross(frame.row_axis, frame.col_axis) @ frame.up, 1.0)  # right-handed, orthonormal
    restored = GroundFrame.from_json(frame.to_json())
    assert np.array_equal(restored.cells(poses[:, :3, 3]), frame.cells(poses[:, :3, 3]))
    # the heading follows the camera's view direction on the grid
    for pose in poses[::10]:
        h = frame.heading(pose[:3, :3])
        step = {0: (-1, 0), 1: (0, 1), 2: (1, 0), 3: (0, -1)}[h]
        ahead = frame.cells((pose[:3, 3] + 0.5 * pose[:3, 2])[None])[0] - frame.cells(pose[:3, 3][None])[0]
        assert np.dot(ahead, step) > 0


def test_grid_puts_walls_objects_and_crossings_where_the_map_has_them():
    poses, t = square_laps()
    wall = wall_points(-0.3, -0.5, 2.5)  # a wall beside the left side of the square
    points = np.concatenate([floor_points(), wall])
    chair = np.array([1.0, 1.0, 0.4])
    grid = build_grid(
        "test", poses, t, points, [("chair", chair), ("cup", np.array([2.0, 2.0, 0.9]))], cell_m=0.25, min_gap_s=5.0
    )
    frame = GroundFrame.from_json(grid.meta["frame"])
    wall_cells = frame.cells(wall[wall[:, 2] > 0.3])
    wall_cells = wall_cells[frame.inside(wall_cells)]
    assert grid.walls[wall_cells[:, 0], wall_cells[:, 1]].mean() > 0.9  # the wall is a wall
    track = frame.cells(poses[:, :3, 3])
    assert not grid.walls[track[:, 0], track[:, 1]].any()  # where the camera went is free
    assert len(grid.features) == 2 and grid.meta["objects"] == ["chair", "cup"]
    chair_cell = frame.cells(chair[None])[0]
    ((fr, fc),) = grid.features[0]
    assert abs(fr - chair_cell[0]) + abs(fc - chair_cell[1]) <= 4  # nearest free cell to the chair
    assert 2 <= grid.n_loops <= 20
    track_set = {tuple(c) for c in track}
    assert all(loop in track_set for loop in grid.loops)  # crossings lie on the trajectory
    GridMap.from_json(grid.to_json())  # a valid, saveable map


def test_crossings_need_separate_passes_and_a_single_pass_map_is_refused():
    cells = np.array([[0, 0], [0, 1], [0, 1], [0, 2], [0, 1]])
    assert crossing_cells(cells, np.array([0, 1, 2, 3, 20.0]), min_gap_s=10) == {(0, 1): 2}
    assert crossing_cells(cells, np.array([0, 1, 2, 3, 5.0]), min_gap_s=10) == {}
    poses, t = square_laps(laps=1)
    with pytest.raises(MapError, match="never crosses"):
        build_grid("once", poses[: len(poses) // 2], t[: len(poses) // 2], floor_points(), [], min_gap_s=5.0)
