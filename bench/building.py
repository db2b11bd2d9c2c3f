"""The simulated building of ``objslam bench isam2`` (bench/isam2.py): ground truth and what the graph is fed.

A simulated robot explores a building: rooms on a grid, two laps in each room, corridors between rooms,
and every fourth visit goes back to a room seen before. The graph gets what the service would give it:
a noisy odometry factor per keyframe (``noisy``), a Huber loop closure when the robot is back within 0.3 m
and 20 deg of a keyframe at least ``LOOP_MIN_AGE`` keyframes old (``revisit`` over the ``cell`` index; at
most one every 10 keyframes), and every third keyframe camera-frame position measurements of up to 4
landmarks (7-8 per room) in view (``in_view``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from graph.geometry import relative

STEP_M = 0.1  # distance between keyframes
ROOM_SPACING_M, ROOM_COLUMNS, LAP_RADIUS_M, WALL_RADIUS_M = 6.0, 7, 1.5, 2.8
ODOMETRY_SIGMA = (0.006, 0.2)  # m, deg: factor sigmas = simulated noise std (VO: 0.08, 3 / sqrt(200 inliers))
LOOP_SIGMA = (0.01, 0.5)
LANDMARK_SIGMA_M = 0.05
LOOP_MIN_AGE, LOOP_EVERY, LOOP_RADIUS_M, LOOP_MAX_DEG = 50, 10, 0.3, 20.0
OBSERVE_EVERY, OBSERVE_MAX, OBSERVE_RANGE_M = 3, 4, 4.0


def camera_pose(position: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """Camera-to-world pose of an upright camera (z forward, y down) at ``position`` looking along ``forward``."""
    z = np.array([forward[0], forward[1], 0.0]) / np.hypot(forward[0], forward[1])
    y = np.array([0.0, 0.0, -1.0])
    T = np.eye(4)
    T[:3, :3] = np.column_stack([np.cross(y, z), y, z])
    T[:3, 3] = position
    return T


@dataclass
class Building:
    """Ground truth: keyframe poses and landmark positions of the simulated exploration."""

    poses: list[np.ndarray]
    landmarks: np.ndarray  # (M, 3)

    @classmethod
    def explore(cls, n_poses: int, n_landmarks: int, rng: np.random.Generator, returns: bool = True) -> Building:
        """Rooms in order; with ``returns`` every fourth visit goes back to a random room seen before."""
        rooms: list[np.ndarray] = []
        poses: list[np.ndarray] = []
        here = np.zeros(3)
        visit = 0
        while len(poses) < n_poses:
            if returns and visit % 4 == 3 and len(rooms) > 2:  # back to a room seen before
                room = rooms[int(rng.integers(len(rooms) - 1))]
            else:
                i = len(rooms)
                row, col = divmod(i, ROOM_COLUMNS)
                room = np.array(
                    [(col if row % 2 == 0 else ROOM_COLUMNS - 1 - col) * ROOM_SPACING_M, row * ROOM_SPACING_M, 1.0]
                )
                rooms.append(room)
            start = float(rng.uniform(0, 2 * math.pi))
            entry = room + LAP_RADIUS_M * np.array([math.cos(start), math.sin(start), 0.0])
            poses += _corridor(here, entry) if poses else []
            poses += _laps(room, start, 2)
            here = poses[-1][:3, 3]
            visit += 1
        return cls(poses[:n_poses], _walls(rooms, n_landmarks, rng))


def _corridor(a: np.ndarray, b: np.ndarray) -> list[np.ndarray]:
    n = max(1, int(np.linalg.norm(b - a) / STEP_M))
    return [camera_pose(a + (b - a) * (i + 1) / n, b - a) for i in range(n)]


def _laps(centre: np.ndarray, start: float, laps: int) -> list[np.ndarray]:
    """Keyframes around a circle in the room, the camera looking outwards at the walls."""
    per_lap = int(2 * math.pi * LAP_RADIUS_M / STEP_M)
    poses = []
    for i in range(laps * per_lap):
        angle = start + 2 * math.pi * i / per_lap
        radial = np.array([math.cos(angle), math.sin(angle), 0.0])
        poses.append(camera_pose(centre + LAP_RADIUS_M * radial, radial))
    return poses


def _walls(rooms: list[np.ndarray], n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` landmarks spread over the rooms' walls at table-to-shelf heights."""
    room = np.arange(n) % len(rooms)
    angle = rng.uniform(0, 2 * math.pi, n)
    height = rng.uniform(-0.5, 0.8, n)
    return np.stack(
        [
            np.array(rooms)[room, 0] + WALL_RADIUS_M * np.cos(angle),
            np.array(rooms)[room, 1] + WALL_RADIUS_M * np.sin(angle),
            np.array(rooms)[room, 2] + height,
        ],
        axis=1,
    )


def noisy(T: np.ndarray, sigma_m: float, sigma_deg: float, rng: np.random.Generator) -> np.ndarray:
    """``T`` times a random pose error: rotation vector and translation drawn per axis with these std."""
    E = np.eye(4)
    E[:3, :3] = Rotation.from_rotvec(rng.normal(0, math.radians(sigma_deg), 3)).as_matrix()
    E[:3, 3] = rng.normal(0, sigma_m, 3)
    return T @ E


def cell(T: np.ndarray) -> tuple[int, int]:
    """The loop-radius grid cell of a pose's position (x, y): ``revisit`` looks in it and its 8 neighbours."""
    return int(T[0, 3] // LOOP_RADIUS_M), int(T[1, 3] // LOOP_RADIUS_M)


def revisit(poses: list[np.ndarray], cells: dict, k: int) -> int | None:
    """The oldest keyframe at least LOOP_MIN_AGE old within the loop radius and angle of keyframe k."""
    T = poses[k]
    cx, cy = cell(T)
    near = sorted(
        i for dx in (-1, 0, 1) for dy in (-1, 0, 1) for i in cells.get((cx + dx, cy + dy), ()) if i <= k - LOOP_MIN_AGE
    )
    for i in near:
        rel = relative(poses[i], T)
        angle = math.degrees(np.linalg.norm(Rotation.from_matrix(rel[:3, :3]).as_rotvec()))
        if np.linalg.norm(rel[:3, 3]) <= LOOP_RADIUS_M and angle <= LOOP_MAX_DEG:
            return i
    return None


def in_view(T: np.ndarray, landmarks: np.ndarray, rng: np.random.Generator) -> list[tuple[int, np.ndarray]]:
    """Up to OBSERVE_MAX landmarks in the camera's field of view and range, with noisy camera-frame positions."""
    inv = np.linalg.inv(T)
    p = landmarks @ inv[:3, :3].T + inv[:3, 3]
    visible = np.nonzero(
        (p[:, 2] > 0.3)
        & (np.linalg.norm(p, axis=1) < OBSERVE_RANGE_M)
        & (np.abs(p[:, 0]) < 0.6 * p[:, 2])
        & (np.abs(p[:, 1]) < 0.5 * p[:, 2])
    )[0]
    visible = visible[np.argsort(p[visible, 2])][:OBSERVE_MAX]
    return [(int(j), p[j] + rng.normal(0, LANDMARK_SIGMA_M, 3)) for j in visible]
