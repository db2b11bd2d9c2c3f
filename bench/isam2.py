"""``objslam bench isam2``: the graph's update cost up to 10,000 poses + 300 landmarks (SPEC 7).

A simulated robot explores a building: rooms on a grid, two laps in each room, corridors between rooms,
and every fourth visit goes back to a room seen before. The graph gets what the service would give it:
a noisy odometry factor per keyframe, a Huber loop closure when the robot is back within 0.3 m and
20 deg of a keyframe at least 150 keyframes old (at most one every 10 keyframes), and every third
keyframe camera-frame position measurements of up to 4 landmarks (7-8 per room) in view. Landmarks
enter the solver once two keyframes saw them (``PoseGraph.add_landmark_observations``).

Timed: each ``ISAM2.update`` call, and each keyframe's graph work (odometry factor, landmark
observations, loop closure with its extra convergence steps).
"""

from __future__ import annotations

import math
import os
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rich.console import Console
from scipy.spatial.transform import Rotation

from bench.report import load_note, markdown_table, record, show_table
from graph.geometry import relative
from graph.interface import Graph
from graph.pose_graph import PoseGraph
from graph.settings import GraphSettings
from graph.window import WindowedGraph

STEP_M = 0.1  # distance between keyframes
ROOM_SPACING_M, ROOM_COLUMNS, LAP_RADIUS_M, WALL_RADIUS_M = 6.0, 7, 1.5, 2.8
ODOMETRY_SIGMA = (0.006, 0.2)  # m, deg: factor sigmas = simulated noise std (VO: 0.08, 3 / sqrt(200 inliers))
LOOP_SIGMA = (0.01, 0.5)
LANDMARK_SIGMA_M = 0.05
LOOP_MIN_AGE, LOOP_EVERY, LOOP_RADIUS_M, LOOP_MAX_DEG = 50, 10, 0.3, 20.0
OBSERVE_EVERY, OBSERVE_MAX, OBSERVE_RANGE_M = 3, 4, 4.0
P95_TARGET_MS, RATIO_TARGET = 20.0, 2.0


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


def _noisy(T: np.ndarray, sigma_m: float, sigma_deg: float, rng: np.random.Generator) -> np.ndarray:
    E = np.eye(4)
    E[:3, :3] = Rotation.from_rotvec(rng.normal(0, math.radians(sigma_deg), 3)).as_matrix()
    E[:3, 3] = rng.normal(0, sigma_m, 3)
    return T @ E


def simulate(
    n_poses: int,
    n_landmarks: int,
    settings: GraphSettings,
    windowed: bool,
    seed: int = 0,
    returns: bool = True,
    loops_and_landmarks: bool = True,
) -> dict:
    """Build the graph keyframe by keyframe; per-update and per-keyframe timings and what went in.

    ``windowed`` False: the whole graph in one iSAM2 (``PoseGraph``), else the service's ``WindowedGraph``, flushed
    at the end (its whole-graph solve applied) before the error is measured. Without ``loops_and_landmarks``
    only the odometry chain is built (iSAM2's cost on the simplest graph).
    """
    rng = np.random.default_rng(seed)
    world = Building.explore(n_poses, n_landmarks, rng, returns)
    graph: Graph = WindowedGraph(settings) if windowed else PoseGraph(settings)
    graph.timings = []
    try:
        result = _build(graph, world, rng, loops_and_landmarks)
    finally:
        if windowed:
            graph.close()
    return result


def _build(graph: Graph, world: Building, rng: np.random.Generator, loops_and_landmarks: bool) -> dict:
    seconds = graph.timings  # the same list through rolls (each new window appends to it)
    for j in range(len(world.landmarks)):
        graph.add_landmark(j)
    cells: dict[tuple[int, int], list[int]] = defaultdict(list)
    per_keyframe, updates_per_keyframe = [], []
    loops = observations = 0
    last_loop = -LOOP_EVERY
    started = time.perf_counter()
    for k, T in enumerate(world.poses):
        seen = _in_view(T, world.landmarks, rng) if k % OBSERVE_EVERY == 0 and loops_and_landmarks else []
        match = _revisit(world.poses, cells, k) if k - last_loop >= LOOP_EVERY and loops_and_landmarks else None
        n_before = len(seconds)
        t0 = time.perf_counter()
        if k == 0:
            graph.add_first(T)
        else:
            odometry = _noisy(relative(world.poses[k - 1], T), *ODOMETRY_SIGMA, rng)
            graph.add_keyframe(odometry, *ODOMETRY_SIGMA)
        if seen:
            graph.add_landmark_observations(k, seen, LANDMARK_SIGMA_M)
        if match is not None:
            graph.add_loop(match, k, _noisy(relative(world.poses[match], T), *LOOP_SIGMA, rng), *LOOP_SIGMA)
        per_keyframe.append(time.perf_counter() - t0)
        updates_per_keyframe.append(len(seconds) - n_before)
        loops += match is not None
        last_loop = k if match is not None else last_loop
        observations += len(seen)
        cells[_cell(T)].append(k)
    update_s, total_s = np.array(seconds), time.perf_counter() - started
    t0 = time.perf_counter()
    graph.flush()  # the window: the whole graph's batch optimum (one iSAM2: nothing to wait for)
    error = np.linalg.norm(graph.poses()[:, :3, 3] - np.array(world.poses)[:, :3, 3], axis=1)
    latencies = np.array(getattr(graph, "solve_latencies", []))
    return {
        "poses": graph.num_keyframes,
        "landmarks": graph.num_landmarks,
        "factors": graph.num_factors,
        "loops": loops,
        "observations": observations,
        "update_s": update_s,
        "keyframe_s": np.array(per_keyframe),
        "updates_per_keyframe": np.array(updates_per_keyframe),
        "total_s": total_s,
        "flush_s": time.perf_counter() - t0,
        "ate_m": float(np.sqrt(np.mean(error**2))),
        "factorization": graph.factorization,
        "solves": len(latencies),
        "solve_s": latencies if len(latencies) else None,
    }


def _cell(T: np.ndarray) -> tuple[int, int]:
    return int(T[0, 3] // LOOP_RADIUS_M), int(T[1, 3] // LOOP_RADIUS_M)


def _revisit(poses: list[np.ndarray], cells: dict, k: int) -> int | None:
    """The oldest keyframe at least LOOP_MIN_AGE old within the loop radius and angle of keyframe k."""
    T = poses[k]
    cx, cy = _cell(T)
    near = sorted(
        i for dx in (-1, 0, 1) for dy in (-1, 0, 1) for i in cells.get((cx + dx, cy + dy), ()) if i <= k - LOOP_MIN_AGE
    )
    for i in near:
        rel = relative(poses[i], T)
        angle = math.degrees(np.linalg.norm(Rotation.from_matrix(rel[:3, :3]).as_rotvec()))
        if np.linalg.norm(rel[:3, 3]) <= LOOP_RADIUS_M and angle <= LOOP_MAX_DEG:
            return i
    return None


def _in_view(T: np.ndarray, landmarks: np.ndarray, rng: np.random.Generator) -> list[tuple[int, np.ndarray]]:
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


def window_mean(seconds: np.ndarray, centre: int, half: int = 100) -> float:
    """Mean over items [centre - half, centre + half), clipped to the run."""
    return float(np.mean(seconds[max(0, centre - half) : min(len(seconds), centre + half)]))


def growth(seconds: np.ndarray, n_poses: int, small: int, large: int) -> float:
    """t(large) / t(small): mean time around ``large`` keyframes over mean time around ``small`` (items are
    keyframes, or updates spread over the run in keyframe order)."""
    scale = len(seconds) / n_poses
    return window_mean(seconds, int(large * scale), int(100 * scale)) / window_mean(
        seconds, int(small * scale), int(100 * scale)
    )


def _ms(seconds: np.ndarray) -> str:
    p50, p95 = np.percentile(seconds * 1e3, [50, 95])
    return f"{p50:.2f} / {p95:.2f} / {seconds.max() * 1e3:.0f}"


@dataclass(frozen=True)
class Variant:
    """One measured configuration: iSAM2 parameters, the window (None: one iSAM2 for the whole graph) and the
    exploration's structure."""

    name: str
    settings: GraphSettings
    windowed: bool
    returns: bool = True
    loops_and_landmarks: bool = True
    repeats: int = 1  # runs of the same simulation; the table shows the one with the median growth ratio

    def params(self) -> str:
        n = self.settings
        where = (
            f"window {n.window_keyframes} + {n.window_step} keyframes, whole graph in a child process"
            if self.windowed
            else "whole graph in one iSAM2"
        )
        return (
            f"{where}; relinearizeThreshold {n.relinearize_threshold:g}, relinearizeSkip {n.relinearize_skip}, "
            f"partial relinearization check {'on' if n.partial_relinearization_check else 'off'}"
        )


def variants() -> list[Variant]:
    """The service's configuration, the same without the window, no returns to old rooms, the bare chain."""
    from service.config import load_settings

    settings = load_settings().graph
    return [
        Variant("**service configuration**", settings, True, repeats=5),
        Variant("whole graph in one iSAM2 (before the window)", settings, False),
        Variant("service, no returns to earlier rooms", settings, True, returns=False),
        Variant("service, odometry chain only", settings, True, loops_and_landmarks=False),
    ]


def run_isam2_bench(console: Console, poses: int, landmarks: int, seed: int, write: Path | None) -> list[dict]:
    """Simulate each variant, print the table and record it in the benchmarks file."""
    small, large = min(1000, poses // 10), poses
    results = []
    for v in variants():
        runs = []
        for _ in range(v.repeats):
            load_before = os.getloadavg()[0]
            r = simulate(poses, landmarks, v.settings, v.windowed, seed, v.returns, v.loops_and_landmarks)
            r.update(
                variant=v.name,
                params=v.params(),
                load=(load_before + os.getloadavg()[0]) / 2,
                ratio=growth(r["keyframe_s"], poses, small, large),
                ratio_updates=growth(r["update_s"], poses, small, large),
                p95_ms=float(np.percentile(r["update_s"] * 1e3, 95)),
            )
            runs.append(r)
            console.print(f"{v.name}: update p95 {r['p95_ms']:.2f} ms, t({large})/t({small}) {r['ratio']:.2f}")
        runs.sort(key=lambda r: r["ratio"])
        r = runs[len(runs) // 2]  # the run with the median ratio
        r["ratios"] = [x["ratio"] for x in runs]
        results.append(r)
    header = ["metric", *(r["variant"] for r in results), "target"]
    metrics = [
        ("iSAM2 parameters", lambda r: r["params"], ""),
        ("poses / landmarks in the solver", lambda r: f"{r['poses']} / {r['landmarks']}", ""),
        ("loop closures / landmark observations", lambda r: f"{r['loops']} / {r['observations']}", ""),
        ("ISAM2.update calls; factorization at the end", lambda r: f"{len(r['update_s'])}; {r['factorization']}", ""),
        ("**update p50 / p95 / max (ms)**", lambda r: _ms(r["update_s"]), f"p95 <= {P95_TARGET_MS:.0f}"),
        ("per keyframe p50 / p95 / max (ms)", lambda r: _ms(r["keyframe_s"]), ""),
        (
            f"mean per keyframe around {small} / {large} poses (ms)",
            lambda r: (
                f"{window_mean(r['keyframe_s'], small) * 1e3:.2f} / {window_mean(r['keyframe_s'], large) * 1e3:.2f}"
            ),
            "",
        ),
        (
            f"**t({large}) / t({small}), per keyframe**",
            lambda r: (
                f"{r['ratio']:.2f}"
                + (
                    f" (median of {len(r['ratios'])} runs: {', '.join(f'{x:.2f}' for x in r['ratios'])})"
                    if len(r["ratios"]) > 1
                    else ""
                )
            ),
            f"<= {RATIO_TARGET:g}",
        ),
        (f"t({large}) / t({small}), per update", lambda r: f"{r['ratio_updates']:.2f}", ""),
        (
            "pose ATE vs the simulated truth, after the final whole-graph solve (cm)",
            lambda r: f"{r['ate_m'] * 100:.1f}",
            "",
        ),
        (
            "whole-graph solves in the child: count; request to estimate p50 / max (s)",
            lambda r: (
                "n/a"
                if r["solve_s"] is None
                else f"{r['solves']}; {np.median(r['solve_s']):.2f} / {r['solve_s'].max():.2f}"
            ),
            "",
        ),
        (
            "run (s); final solve (s); load average (2 cores, shared)",
            lambda r: f"{r['total_s']:.0f}; {r['flush_s']:.1f}; {r['load']:.1f}",
            "",
        ),
    ]
    rows = [[name, *(cell(r) for r in results), target] for name, cell, target in metrics]
    show_table(console, f"iSAM2 at {poses} poses + {landmarks} landmarks", header, rows)
    notes = (
        "Simulated exploration of a building: rooms 6 m apart on a grid, two 1.5 m-radius laps per room, "
        "straight corridors between rooms, every fourth visit back to a random earlier room (except in the "
        f"no-returns variant); keyframes {STEP_M} m apart; odometry noise {ODOMETRY_SIGMA[0] * 100:g} cm / "
        f"{ODOMETRY_SIGMA[1]:g} deg per keyframe (the visual front end's sigmas at ~200 inliers); a Huber loop "
        f"closure when back within {LOOP_RADIUS_M} m and {LOOP_MAX_DEG:g} deg of a keyframe >= {LOOP_MIN_AGE} "
        f"keyframes old (at most one per {LOOP_EVERY} keyframes, then up to 10 convergence updates, as in the "
        f"service); every {OBSERVE_EVERY}rd keyframe up to {OBSERVE_MAX} landmarks in view (range "
        f"{OBSERVE_RANGE_M:g} m) measured in the camera frame with {LANDMARK_SIGMA_M * 100:g} cm noise, a "
        "landmark entering the solver once two keyframes saw it (the last variant: the odometry factors only, "
        "which shows the growth of gtsam's own per-update cost with the number of variables). "
        "Service configuration: a bounded iSAM2 window over the newest keyframes (older ones fixed in it), "
        "rolled forward and rebuilt every window-step keyframes at the newest estimate of the whole graph, "
        "which a child process solves (graph/window.py); the whole-graph variant is the one iSAM2 the service "
        "used before. Update = one ISAM2.update call of the foreground solver (the window's rebuilds at rolls "
        "included); per keyframe = "
        "all of a keyframe's graph calls (odometry, observations, loop closure and its convergence updates, "
        "estimate of the newest pose after each update, a roll); t(N) = mean over the 200 keyframes around N "
        "(the last 200 at the end of the run), per update the same window in update order; the service "
        "configuration is run 5 times (the same simulation: the spread is the machine's timing noise) and the "
        "column shows the run with the median ratio. CHOLESKY "
        "factorization and cached linearized factors throughout (QR and no cache measured no better). Load = "
        "1-minute load average on the 2 shared cores during the variant." + load_note(max(r["load"] for r in results))
    )
    path = record(
        "isam2",
        f"iSAM2 update cost at {poses} poses + {landmarks} landmarks",
        f"objslam bench isam2 --poses {poses} --landmarks {landmarks} --seed {seed}",
        markdown_table(header, rows),
        notes,
        write,
    )
    console.print(f"recorded in {path}")
    return results
