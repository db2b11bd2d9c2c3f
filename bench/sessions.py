"""Second sessions on a stored map: from random places inside it, how soon they relocalize, whether falsely,
and how well they then lie in the first session's frame.

Per map (a synthetic room of a seed never used for tuning): session 1 maps one lap and is checkpointed into
a map store, as ``serve --state-dir`` does. Each start then restores the map from the store (a fresh core, as
a restart would), begins a session (``SlamCore.begin_session``) and feeds the frames of the second lap from a
random frame on, 1000 s later, so the robot is somewhere the map has seen but tracking cannot know where.

Per start: frames until the session's newest keyframe is tied to the map (localized); a false relocalization
is a localized keyframe more than ``FALSE_M`` from the truth in the first session's frame (session 1 aligned
to the ground truth by Umeyama, in the map as it is at the end); the second session's ATE in that frame (no
alignment of its own), against session 1's ATE.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from bench.report import markdown_table, record, show_table
from evaluation.trajectory_metrics import umeyama
from service.config import load_settings
from service.map_store import MapStore
from slam.build import build_core
from slam.core import SlamCore
from slam.parts import COLD, CoreParts, assemble, core_parts
from slam.snapshot import restore_core
from sources import open_dataset
from sources.base import truth_per_frame

HELD_OUT_SEEDS = (11, 12)  # never used for tuning anything
STARTS_PER_MAP = 5
SESSION_FRAMES = 40
FALSE_M = 0.3
LATER_S = 1000.0
SPEC = "synthetic:room?seed={seed}&frames=300&fps=10&width=320&height=240&revolutions=2"
HEADER = [
    "map seed",
    "start frame",
    "localized after (frames)",
    "against keyframe",
    "false",
    "session 2 ATE in map frame (cm)",
    "session 1 ATE (cm)",
    "session 1 ATE there (cm)",
]


@dataclass(frozen=True)
class Start:
    seed: int
    frame: int
    localized_after: int | None
    against: int | None
    false: bool
    ate_m: float
    map_ate_m: float
    here_ate_m: float  # session 1's ATE over the same places (a lap earlier)


def _ate(poses: np.ndarray, truth: np.ndarray, T: np.ndarray) -> float:
    p = poses[:, :3, 3] @ T[:3, :3].T + T[:3, 3]
    return float(np.sqrt(np.mean(np.sum((p - truth[:, :3, 3]) ** 2, axis=1))))


def map_session(seed: int, path: Path) -> int:
    """Session 1 over the first lap, checkpointed after every keyframe into ``path``; its number of frames."""
    settings, ds = load_settings(), open_dataset(SPEC.format(seed=seed))
    lap = len(ds) // 2
    core, store = build_core(settings), MapStore(path, settings.robot, COLD)
    for i in range(lap):
        core.step(ds.frame(i))
        parts = core_parts(core)
        store.checkpoint(parts.small, parts.logs, core.graph.num_keyframes, i + 1)
    store.close()
    core.close()
    return lap


def second_session(seed: int, path: Path, start: int) -> Start:
    """A fresh core from the store, a session from frame ``start`` on, 1000 s later. Errors are measured in the
    map as it is at the end (the first session's loop closures still pending at its last checkpoint, and the
    second session's own, move it): session 1 aligned to the truth then, session 2 in that frame."""
    settings, ds = load_settings(), open_dataset(SPEC.format(seed=seed))
    store = MapStore(path, settings.robot, COLD)
    loaded = store.load()
    assert loaded is not None
    core: SlamCore = restore_core(settings, assemble(CoreParts(loaded.small, loaded.logs), materialize=False))
    core.begin_session(settings.persistence.session_gap_s)
    truth = truth_per_frame(ds)
    localized_after, frame_of, placed = None, {}, None  # frame_of: keyframe -> its frame index
    for n, i in enumerate(range(start, min(len(ds), start + SESSION_FRAMES))):
        frame = ds.frame(i)
        core.step(replace(frame, timestamp=frame.timestamp + LATER_S))
        k = core.graph.num_keyframes - 1
        if core.records[-1].is_keyframe:
            frame_of[k] = i
        first = core.session_keyframe
        if localized_after is None and first is not None and k >= first and core.segments.tied(k):
            localized_after, placed = n + 1, k
    traj = core.trajectory(tied_only=True)
    mine = traj.timestamps > LATER_S
    index = {round(float(t), 6): i for i, t in enumerate(ds.timestamps)}
    frames = [index[round(float(t) - (LATER_S if m else 0.0), 6)] for t, m in zip(traj.timestamps, mine, strict=True)]
    ones, twos = (
        [f for f, m in zip(frames, mine, strict=True) if not m],
        [f for f, m in zip(frames, mine, strict=True) if m],
    )
    T = umeyama(traj.poses[~mine, :3, 3], truth[ones, :3, 3])  # the map's frame -> the true world
    map_ate, lap = _ate(traj.poses[~mine], truth[ones], T), len(ones)
    ate = _ate(traj.poses[mine], truth[twos], T) if twos else float("nan")
    there = [f - lap for f in twos if 0 <= f - lap < lap]  # the same places in session 1 (frame order = index)
    here = _ate(traj.poses[~mine][there], truth[there], T) if there else float("nan")
    false = placed is not None and bool(
        np.linalg.norm((T @ core.graph.pose(placed))[:3, 3] - truth[frame_of[placed], :3, 3]) > FALSE_M
    )
    against = core.segments.last_match if localized_after is not None else None
    core.close()
    store.close()
    return Start(seed, start, localized_after, against, false, ate, map_ate, here)


def measure(seeds: tuple[int, ...] = HELD_OUT_SEEDS, starts: int = STARTS_PER_MAP) -> list[Start]:
    rng = np.random.default_rng(0)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            path = Path(tmp) / f"map-{seed}.db"
            lap = map_session(seed, path)
            for start in sorted(rng.integers(lap, 2 * lap - SESSION_FRAMES, starts)):
                results.append(second_session(seed, path, int(start)))
    return results


def run_sessions_bench(console, write: Path | None, seeds: tuple[int, ...] = HELD_OUT_SEEDS) -> list[Start]:
    results = measure(seeds)
    rows = [
        [
            r.seed,
            r.frame,
            "never" if r.localized_after is None else r.localized_after,
            "-" if r.against is None else r.against,
            "yes" if r.false else "no",
            round(r.ate_m * 100, 2),
            round(r.map_ate_m * 100, 2),
            round(r.here_ate_m * 100, 2),
        ]
        for r in results
    ]
    show_table(console, "Second sessions on a stored map", HEADER, rows)
    within = sum(1 for r in results if r.localized_after is not None and r.localized_after <= 30)
    false = sum(r.false for r in results)
    ratios = [r.ate_m / r.map_ate_m for r in results if r.localized_after is not None]
    worst, median = (max(ratios), float(np.median(ratios))) if ratios else (float("nan"), float("nan"))
    summary = (
        f"{within} of {len(results)} starts localized within 30 frames (target >= 9 of 10); {false} false "
        f"relocalizations (target 0); second-session ATE {median:.2f} x the first session's (median), "
        f"{worst:.2f} x at most, {sum(x > 2 for x in ratios)} of {len(ratios)} over 2 x (target <= 2)."
    )
    console.print(summary)
    if write is not None:
        notes = (
            f"{summary} Maps: synthetic rooms of held-out seeds {', '.join(map(str, seeds))} (never used for "
            f"tuning), session 1 over the first lap (a checkpoint per keyframe into a map store); each start a "
            f"fresh core restored from the store, {SESSION_FRAMES} frames of the second lap from a random frame, "
            f"{LATER_S:.0f} s later. Localized: the session's newest keyframe tied to the map (relocalization "
            f"against the stored keyframes: appearance candidates, PnP with the loop-closure thresholds). False: "
            f"the first localized keyframe over {FALSE_M} m from the truth in session 1's frame (session 1 "
            "aligned to the truth by Umeyama, in the map as it stands at the end). ATE: session 2's tied frames "
            "in session 1's frame, no alignment of their "
            "own; 'session 1 ATE there': session 1's own error over the same places a lap earlier (what a session "
            "localized against them inherits)."
        )
        cmd = "objslam bench sessions"
        title = "Second sessions: relocalization in a stored map"
        record("sessions", title, cmd, markdown_table(HEADER, rows), notes, write)
    return results
