"""Synthetic room scene: object layout, handheld orbit trajectory, drifting odometry and true loops.

World frame: z up, floor at z = 0, metres; the room spans [0, 6] x [0, 5] x [0, 2.6].
Camera poses are camera-to-world 4x4 with the OpenCV camera frame (x right, y down, z forward).
Everything here is pure math and deterministic given the seed.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from graph.geometry import inverse
from sources.base import ObjectTruth

ROOM_SIZE: tuple[float, float, float] = (6.0, 5.0, 2.6)
LIGHT: tuple[float, float, float] = (3.0, 2.5, 2.45)
CLEARANCE_M = 0.7  # minimum horizontal distance from any camera position to any object footprint

# label, centre x, centre y, size (x, y, z), yaw, support index (-1 floor, -2 wall-mounted), xy / yaw jitter
_LAYOUT: list[tuple[str, float, float, tuple[float, float, float], float, int, float, float]] = [
    ("dining table", 5.45, 2.5, (0.8, 1.4, 0.75), 0.0, -1, 0.06, 0.04),
    ("cup", 5.22, 2.2, (0.08, 0.08, 0.1), 0.0, 0, 0.03, 3.0),
    ("cup", 5.22, 2.5, (0.08, 0.08, 0.1), 0.0, 0, 0.03, 3.0),
    ("cup", 5.22, 2.8, (0.08, 0.08, 0.1), 0.0, 0, 0.03, 3.0),
    ("laptop", 5.58, 2.45, (0.24, 0.34, 0.03), 0.0, 0, 0.03, 0.2),
    ("bottle", 5.6, 2.95, (0.08, 0.08, 0.28), 0.0, 0, 0.03, 3.0),
    ("chair", 5.45, 1.45, (0.46, 0.46, 0.9), 0.0, -1, 0.05, 0.15),
    ("chair", 5.45, 3.55, (0.46, 0.46, 0.9), np.pi, -1, 0.05, 0.15),
    ("couch", 0.48, 2.5, (0.9, 2.0, 0.85), 0.0, -1, 0.04, 0.0),
    ("book", 0.45, 2.0, (0.16, 0.23, 0.04), 0.3, 8, 0.05, 0.6),
    ("tv", 3.0, 4.96, (1.1, 0.06, 0.65), 0.0, -2, 0.2, 0.0),
    ("potted plant", 5.5, 4.5, (0.45, 0.45, 0.8), 0.0, -1, 0.06, 1.0),
    ("refrigerator", 0.9, 0.41, (0.75, 0.7, 1.8), 0.0, -1, 0.1, 0.0),
    ("chair", 3.3, 0.45, (0.46, 0.46, 0.9), np.pi / 2, -1, 0.1, 0.3),
    ("chair", 1.4, 4.5, (0.46, 0.46, 0.9), -np.pi / 2, -1, 0.1, 0.3),
]
_TV_BOTTOM_M = 1.0


def look_rotation(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Camera-to-world rotations (N, 3, 3) looking along heading ``yaw`` tilted up by ``pitch``, rolled."""
    cp, sp = np.cos(pitch), np.sin(pitch)
    fwd = np.stack([cp * np.cos(yaw), cp * np.sin(yaw), sp], axis=-1)
    right = np.stack([np.sin(yaw), -np.cos(yaw), np.zeros_like(yaw)], axis=-1)
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd], axis=-1)
    return R @ Rotation.from_rotvec(np.outer(roll, [0.0, 0.0, 1.0])).as_matrix()


def _smooth_jitter(rng: np.random.Generator, t: np.ndarray, amplitude: float, dims: int) -> np.ndarray:
    """Handheld tremor: per dimension a sum of three sinusoids (0.3-1.5 Hz), shape (N, dims)."""
    freq = rng.uniform(0.3, 1.5, (3, dims))
    phase = rng.uniform(0.0, 2.0 * np.pi, (3, dims))
    amp = amplitude * rng.uniform(0.5, 1.0, (3, dims))
    return np.sum(amp * np.sin(2.0 * np.pi * freq * t[:, None, None] + phase), axis=1)


def orbit_trajectory(frames: int, fps: float, seed: int, revolutions: float = 1.15) -> np.ndarray:
    """True camera-to-world poses (N, 4, 4): a jittered elliptic orbit, looking outward, > 1 turn."""
    rng = np.random.default_rng([seed, 11])
    ph = rng.uniform(0.0, 2.0 * np.pi, 6)
    theta = rng.uniform(0.0, 2.0 * np.pi) + 2.0 * np.pi * revolutions * np.arange(frames) / frames
    t = np.arange(frames) / fps
    centre = np.array([3.0, 2.5]) + rng.uniform(-0.08, 0.08, 2)
    scale = 1.0 + 0.06 * np.sin(2.0 * theta + ph[0])
    pos = np.stack(
        [
            centre[0] + 1.0 * scale * np.cos(theta),
            centre[1] + 0.75 * scale * np.sin(theta),
            1.4 + 0.1 * np.sin(theta + ph[1]),
        ],
        axis=-1,
    )
    pos += _smooth_jitter(rng, t, 0.004, 3)
    ang = _smooth_jitter(rng, t, np.deg2rad(0.3), 3)
    yaw = theta + 0.15 * np.sin(3.0 * theta + ph[2]) + ang[:, 0]
    pitch = -0.3 + 0.07 * np.sin(2.0 * theta + ph[3]) + ang[:, 1]
    roll = 0.03 * np.sin(theta + ph[4]) + ang[:, 2]
    poses = np.tile(np.eye(4), (frames, 1, 1))
    poses[:, :3, :3] = look_rotation(yaw, pitch, roll)
    poses[:, :3, 3] = pos
    return poses


def look_up(poses: np.ndarray, first: int, last: int, angle: float) -> np.ndarray:
    """The poses with the camera pitched up between frames ``first`` and ``last`` by a smooth bump that peaks
    at ``angle`` radians half-way: a view that turns away from the room to the plain wall tops and ceiling."""
    out = poses.copy()
    n = max(1, last - first)
    for i in range(max(0, first), min(len(poses), last + 1)):
        a = angle * 0.5 * (1.0 - np.cos(2.0 * np.pi * (i - first) / n))
        out[i, :3, :3] = poses[i, :3, :3] @ Rotation.from_rotvec([a, 0.0, 0.0]).as_matrix()  # x right, y down: up
    return out


BLANK_STRETCH = (0.30, 0.42)
"""``blank`` scene: the fractions of the sequence between which the camera looks up at the plain walls."""
BLANK_PITCH_RAD = 1.2


def _footprint(center: np.ndarray, size: tuple[float, float, float], yaw: float) -> np.ndarray:
    """The four xy corners (4, 2) of a yawed box footprint."""
    c, s = np.cos(yaw), np.sin(yaw)
    hx, hy = size[0] / 2.0, size[1] / 2.0
    local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    return center[:2] + local @ np.array([[c, s], [-s, c]])


def _overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """True when two convex quadrilaterals intersect (separating axis test)."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        for n in np.stack([-edges[:, 1], edges[:, 0]], axis=1):
            pa, pb = a @ n, b @ n
            if pa.max() <= pb.min() or pb.max() <= pa.min():
                return False
    return True


def _min_distance(points: np.ndarray, center: np.ndarray, size: tuple[float, float, float], yaw: float) -> float:
    """Smallest horizontal distance from ``points`` (N, 2) to a yawed box footprint."""
    c, s = np.cos(yaw), np.sin(yaw)
    d = points - center[:2]
    local = np.abs(np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1))
    out = np.maximum(local - np.array(size[:2]) / 2.0, 0.0)
    return float(np.min(np.linalg.norm(out, axis=1)))


def _candidate(entry: tuple, placed: list[ObjectTruth], rng: np.random.Generator, jitter: bool) -> ObjectTruth:
    """One jittered placement of a layout entry (on the floor, on its support, or on the wall)."""
    label, x, y, size, yaw, support, pos_j, yaw_j = entry
    k = 1.0 if jitter else 0.0
    dx, dy = rng.uniform(-pos_j, pos_j, 2) * k
    if support == -2:  # wall-mounted: slides along the wall only
        dy = 0.0
    yaw = float(yaw + rng.uniform(-yaw_j, yaw_j) * k)
    if support >= 0:
        base = placed[support]
        z0 = base.center[2] + base.size[2] / 2.0
    else:
        z0 = _TV_BOTTOM_M if support == -2 else 0.0
    return ObjectTruth(len(placed) + 1, label, (x + dx, y + dy, z0 + size[2] / 2.0), size, yaw)


def _valid(obj: ObjectTruth, support: int, placed: list[ObjectTruth], cams: np.ndarray) -> bool:
    """Inside the room and its support, clear of the camera path and of objects on the same level."""
    poly = _footprint(np.array(obj.center), obj.size, obj.yaw)
    if np.any(poly < 0.005) or np.any(poly > np.array(ROOM_SIZE[:2]) - 0.005):
        return False
    if _min_distance(cams, np.array(obj.center), obj.size, obj.yaw) < CLEARANCE_M:
        return False
    if support >= 0:
        base = placed[support]
        if not _inside(poly, np.array(base.center), (base.size[0] - 0.04, base.size[1] - 0.04), base.yaw):
            return False
    # placed holds the objects of the first len(placed) layout entries, in layout order
    for other, other_support in zip(placed, [e[5] for e in _LAYOUT[: len(placed)]], strict=True):
        same_level = (support >= 0) == (other_support >= 0)
        if same_level and _overlap(poly, _footprint(np.array(other.center), other.size, other.yaw)):
            return False
    return True


def _inside(points: np.ndarray, center: np.ndarray, size: tuple[float, float], yaw: float) -> bool:
    """True when all ``points`` (N, 2) lie inside a yawed rectangle."""
    c, s = np.cos(yaw), np.sin(yaw)
    d = points - center[:2]
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)
    return bool(np.all(np.abs(local) <= np.array(size) / 2.0))


def place_objects(seed: int, camera_positions: np.ndarray) -> list[ObjectTruth]:
    """The jittered room layout (ids from 1), rejection-sampled to avoid overlaps and the camera path."""
    rng = np.random.default_rng([seed, 13])
    cams = np.asarray(camera_positions)[:, :2]
    placed: list[ObjectTruth] = []
    for entry in _LAYOUT:
        for attempt in range(60):
            obj = _candidate(entry, placed, rng, jitter=attempt < 59)
            if attempt == 59 or _valid(obj, entry[5], placed, cams):
                break
        placed.append(obj)
    return placed


def drifting_odometry(poses: np.ndarray, seed: int, drift: float = 1.0) -> np.ndarray:
    """Odometry poses: true relative motions with per-frame noise (2 mm, 0.05 deg) and a yaw bias."""
    rng = np.random.default_rng([seed, 17])
    n = len(poses)
    rot_noise = rng.normal(0.0, np.deg2rad(0.05), (n, 3)) * drift
    trans_noise = rng.normal(0.0, 0.002, (n, 3)) * drift
    up_cam = np.einsum("nji,j->ni", poses[:, :3, :3], np.array([0.0, 0.0, 1.0]))
    rotvec = rot_noise + up_cam * np.deg2rad(0.02) * drift
    noise = np.tile(np.eye(4), (n, 1, 1))
    noise[:, :3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    noise[:, :3, 3] = trans_noise
    out = np.empty_like(poses)
    out[0] = poses[0]
    for k in range(1, n):
        out[k] = out[k - 1] @ inverse(poses[k - 1]) @ poses[k] @ noise[k]
    return out


def find_loops(
    poses: np.ndarray, min_gap: int, max_dist: float = 0.3, max_angle_deg: float = 20.0
) -> list[tuple[int, int]]:
    """All sorted pairs (i, j), j - i >= min_gap, whose poses are within ``max_dist`` m and ``max_angle_deg``."""
    pos, rot = poses[:, :3, 3], poses[:, :3, :3]
    cos_max = 1.0 + 2.0 * np.cos(np.deg2rad(max_angle_deg))  # trace threshold
    pairs: list[tuple[int, int]] = []
    for start in range(0, len(poses), 256):
        rows = np.arange(start, min(start + 256, len(poses)))
        dist = np.linalg.norm(pos[rows, None] - pos[None], axis=-1)
        trace = np.einsum("iab,jab->ij", rot[rows], rot)
        gap = np.arange(len(poses))[None] - rows[:, None]
        ii, jj = np.nonzero((gap >= min_gap) & (dist <= max_dist) & (trace >= cos_max))
        pairs.extend(zip((rows[ii]).tolist(), jj.tolist(), strict=True))
    return sorted(pairs)
