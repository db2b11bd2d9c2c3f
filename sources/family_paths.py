"""Camera paths of the synthetic scene family (``sources.scene_family``): four kinds, speed- and yaw-rate capped.

A path is planned from the room alone (``plan_path``): its geometry is a periodic curve of a cycle parameter
``u`` (one lap, one round trip or one sweep cycle per unit), giving the camera's horizontal position and its
base heading. ``path_poses`` then walks ``cycles`` cycles of it in ``frames / fps`` seconds: as fast as the
scene's speed and yaw-rate limits allow where the curve is demanding, at an even pace elsewhere, and stopping
short when the limits do not allow all the cycles in that time. Heights, pitch, a look-around oscillation and
handheld tremor are functions of time. Kinds:

- ``inward``: laps of an ellipse 1.3-1.7 m from the walls, looking at the room centre;
- ``outward``: laps of an ellipse 1.5-2.5 m from the walls (at least 0.45 m around the centre), looking out;
- ``walk``: round trips along a thin loop down the room's long axis, looking where it walks;
- ``sweep``: standing near one spot and sweeping the view across the room (100-200 degrees), stepping slowly.

Yaw rate (heading of the optical axis about world z) is at most ``MAX_YAW_RATE_DEG_S``: the smooth part is
capped at the scene's ``yaw_rate_deg_s`` (30-51 deg/s), tremor adds at most 8.5 deg/s. Pure math, deterministic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sources.scene import _smooth_jitter as smooth_jitter
from sources.scene import look_rotation

PATH_KINDS: tuple[str, ...] = ("inward", "outward", "walk", "sweep")
MAX_YAW_RATE_DEG_S = 60.0
_TREMOR_DEG = 0.3  # angular tremor amplitude per sinusoid (3 sinusoids, <= 1.5 Hz: <= 8.5 deg/s)
_SAMPLES_PER_CYCLE = 4000


@dataclass(frozen=True)
class PathPlan:
    """A planned camera path: the curve (``kind``, centre, semi-axes, direction, offsets) and its limits."""

    kind: str
    centre: tuple[float, float]
    axes: tuple[float, float]  # ellipse semi-axes (x, y); sweep: (half step length, 0)
    theta0: float  # start phase (rad); sweep: the base heading
    direction: float  # +1 counter-clockwise, -1 clockwise; sweep: the stepping direction (rad)
    look_offset: float  # constant heading offset (rad); sweep: the sweep half-range
    sweeps: int  # sweep: view sweeps per stepping cycle
    wobble: tuple[float, float]  # ellipse radius wobble (amplitude, phase)
    speed_mps: float  # translation limit
    yaw_rate_deg_s: float  # smooth-yaw limit (look-around included)
    look_around: tuple[float, float, float]  # amplitude (rad), frequency (Hz), phase of the heading oscillation
    height: tuple[float, float, float]  # mean camera height (m), amplitude, phase
    pitch: tuple[float, float, float]  # mean pitch (rad, negative = down), amplitude, phase
    tremor_m: float


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Angles wrapped to [-pi, pi)."""
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


def curve(plan: PathPlan, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal positions (N, 2) and continuous base headings (N,) at cycle parameters ``u`` (period 1)."""
    u = np.asarray(u, float)
    cx, cy = plan.centre
    a, b = plan.axes
    if plan.kind == "sweep":
        step = a * np.sin(2.0 * np.pi * u)
        xy = np.stack([cx + step * np.cos(plan.direction), cy + step * np.sin(plan.direction)], axis=1)
        return xy, plan.theta0 + plan.look_offset * np.sin(2.0 * np.pi * plan.sweeps * u)
    theta = plan.theta0 + plan.direction * 2.0 * np.pi * u
    w, phase = plan.wobble
    scale = 1.0 + w * np.sin(2.0 * theta + phase)
    xy = np.stack([cx + a * scale * np.cos(theta), cy + b * scale * np.sin(theta)], axis=1)
    if plan.kind == "walk":  # along the direction of travel: the ellipse's tangent, within 90 deg of the circle's
        ds = 2.0 * w * np.cos(2.0 * theta + phase)
        dx = plan.direction * a * (ds * np.cos(theta) - scale * np.sin(theta))
        dy = plan.direction * b * (ds * np.sin(theta) + scale * np.cos(theta))
        ref = theta + plan.direction * np.pi / 2.0
    else:  # along the ray from the centre (outward) or against it (inward)
        dx, dy = a * scale * np.cos(theta), b * scale * np.sin(theta)
        ref = theta
        if plan.kind == "inward":
            dx, dy, ref = -dx, -dy, theta + np.pi
    return xy, ref + _wrap(np.arctan2(dy, dx) - ref) + plan.look_offset


def plan_path(kind: str, room: tuple[float, float, float], rng: np.random.Generator) -> PathPlan:
    """A random path of ``kind`` inside a room [0, W] x [0, D] (walls at least 0.9 m away)."""
    w, d = room[0], room[1]
    centre = (w / 2.0, d / 2.0)
    theta0, offset = rng.uniform(0.0, 2.0 * np.pi), rng.uniform(-0.25, 0.25)
    direction = float(rng.choice([-1.0, 1.0]))
    sweeps = 1
    if kind == "inward":
        margin = rng.uniform(1.3, 1.7)
        axes = (max(w / 2.0 - margin, 0.35), max(d / 2.0 - margin, 0.35))
    elif kind == "outward":
        axes = (max(w / 2.0 - rng.uniform(1.5, 2.5), 0.45), max(d / 2.0 - rng.uniform(1.5, 2.5), 0.45))
    elif kind == "walk":
        long_x = w >= d
        length, across = (w, d) if long_x else (d, w)
        half = (length / 2.0 - rng.uniform(1.0, 1.4), rng.uniform(0.3, 0.6))
        axes = half if long_x else (half[1], half[0])
        shift = rng.uniform(-1.0, 1.0) * max(across / 2.0 - half[1] - 1.3, 0.0)
        centre = (centre[0], centre[1] + shift) if long_x else (centre[0] + shift, centre[1])
        offset = 0.0
    elif kind == "sweep":
        spot = np.array([rng.uniform(1.2, w - 1.2), rng.uniform(1.2, d - 1.2)])
        to_centre = np.array(centre) - spot
        base = np.arctan2(to_centre[1], to_centre[0]) if np.linalg.norm(to_centre) > 0.5 else rng.uniform(-np.pi, np.pi)
        step_dir = base + np.pi / 2.0 + rng.uniform(-0.5, 0.5)
        room_left = min(spot[0] - 1.0, w - 1.0 - spot[0], spot[1] - 1.0, d - 1.0 - spot[1])
        axes = (float(np.clip(rng.uniform(0.2, 0.6), 0.0, max(room_left, 0.0))), 0.0)
        centre, direction, offset = (float(spot[0]), float(spot[1])), float(step_dir), rng.uniform(0.87, 1.75)
        sweeps = int(rng.integers(2, 4))
        theta0 = float(base)
    else:
        raise ValueError(f"unknown path kind {kind!r}; known: {', '.join(PATH_KINDS)}")
    yaw_rate = rng.uniform(30.0, 51.0)
    amp = rng.uniform(0.1, 0.45) if kind != "sweep" else 0.0
    freq = min(rng.uniform(0.05, 0.2), 0.4 * np.deg2rad(yaw_rate) / (2.0 * np.pi * max(amp, 1e-9)))
    return PathPlan(
        kind=kind,
        centre=(float(centre[0]), float(centre[1])),
        axes=(float(axes[0]), float(axes[1])),
        theta0=float(theta0),
        direction=direction,
        look_offset=float(offset),
        sweeps=sweeps,
        wobble=(rng.uniform(0.0, 0.06) if kind != "walk" else 0.0, rng.uniform(0.0, 2.0 * np.pi)),
        speed_mps=rng.uniform(0.5, 1.0) if kind != "sweep" else rng.uniform(0.15, 0.3),
        yaw_rate_deg_s=float(yaw_rate),
        look_around=(float(amp), float(freq), rng.uniform(0.0, 2.0 * np.pi)),
        height=(rng.uniform(1.25, 1.6), rng.uniform(0.0, 0.08), rng.uniform(0.0, 2.0 * np.pi)),
        pitch=(rng.uniform(-0.45, -0.2), rng.uniform(0.03, 0.12), rng.uniform(0.0, 2.0 * np.pi)),
        tremor_m=0.004 if kind != "sweep" else 0.006,
    )


def path_points(plan: PathPlan, spacing_m: float = 0.02) -> np.ndarray:
    """Horizontal positions (N, 2) along one whole cycle, at most ``spacing_m`` apart (for clearance tests)."""
    xy, _ = curve(plan, np.linspace(0.0, 1.0, _SAMPLES_PER_CYCLE, endpoint=False))
    step = float(np.max(np.linalg.norm(np.diff(xy, axis=0), axis=1), initial=0.0))
    return xy[:: max(1, int(spacing_m / max(step, 1e-9)))]


def _schedule(plan: PathPlan, cycles: float, duration: float) -> tuple[np.ndarray, np.ndarray]:
    """Cycle parameters and their times: limit-bound where needed, an even pace elsewhere, cut at ``duration``."""
    n = max(2, int(np.ceil(cycles * _SAMPLES_PER_CYCLE)))
    u = np.linspace(0.0, cycles, n + 1)
    xy, heading = curve(plan, u)
    ds = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    dh = np.abs(np.diff(heading))
    amp, freq, _ = plan.look_around
    base_rate = np.deg2rad(plan.yaw_rate_deg_s) - amp * 2.0 * np.pi * freq
    need = np.maximum(ds / plan.speed_mps, dh / base_rate)  # the least time each step takes
    if need.sum() < duration:  # walk the rest at an even pace: sum(max(need, pace)) == duration
        lo, hi = 0.0, duration / n
        for _ in range(60):
            mid = (lo + hi) / 2.0
            lo, hi = (mid, hi) if np.maximum(need, mid).sum() < duration else (lo, mid)
        need = np.maximum(need, hi)
    return u, np.concatenate([[0.0], np.cumsum(need)])


def path_poses(plan: PathPlan, frames: int, fps: float, cycles: float, seed: int) -> np.ndarray:
    """True camera-to-world poses (frames, 4, 4) walking ``cycles`` cycles of the path in ``frames / fps`` s."""
    rng = np.random.default_rng([seed, 1011])
    t = np.arange(frames) / fps
    grid_u, grid_t = _schedule(plan, cycles, max(t[-1], 1e-6))
    u = np.interp(t, grid_t, grid_u)
    xy, heading = curve(plan, u)
    amp, freq, phase = plan.look_around
    ang = smooth_jitter(rng, t, np.deg2rad(_TREMOR_DEG), 3)
    yaw = heading + amp * np.sin(2.0 * np.pi * freq * t + phase) + ang[:, 0]
    h_mean, h_amp, h_phase = plan.height
    p_mean, p_amp, p_phase = plan.pitch
    slow = 2.0 * np.pi * 0.07 * t
    pitch = p_mean + p_amp * np.sin(slow + p_phase) + ang[:, 1]
    roll = 0.03 * np.sin(0.5 * slow + h_phase) + ang[:, 2]
    pos = np.column_stack([xy, h_mean + h_amp * np.sin(slow * 0.8 + h_phase)])
    pos += smooth_jitter(rng, t, plan.tremor_m, 3)
    poses = np.tile(np.eye(4), (frames, 1, 1))
    poses[:, :3, :3] = look_rotation(yaw, pitch, roll)
    poses[:, :3, 3] = pos
    return poses


def heading_rates_deg_s(poses: np.ndarray, fps: float) -> np.ndarray:
    """Yaw rate (deg/s) between consecutive poses: the change of the optical axis' heading about world z."""
    fwd = poses[:, :3, 2]
    heading = np.unwrap(np.arctan2(fwd[:, 1], fwd[:, 0]))
    return np.abs(np.diff(heading)) * fps * 180.0 / np.pi
