"""``objslam bench policy-loops``: the two-pass RL loop-closure workflow on real and synthetic data (issue 6).

Per dataset (frames replayed without odometry, so the visual front end runs):
1. first pass with appearance loop candidates: builds the map, its ``grid.json``, and gives the
   "appearance" row;
2. a policy is trained for that grid world (``train-lc --from-map``) and exported to ONNX;
3. second pass with the policy as the only candidate source ("policy" row). The "odometry only" row is
   the front end's own trajectory (``odometry.tum``) of the first pass: the same visual odometry runs in
   both passes, loop closures only change the graph.
Every accepted loop is judged against ground truth as in ``bench loops``.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

from rich.console import Console

from bench.report import markdown_table, record, show_table
from bench.slam import default_datasets, run_one
from rl.map_files import GRID_FILE


def train_policy(run_dir: Path, out: Path, steps: int, init_from: Path | None = None) -> dict[str, Any]:
    """Train and export a policy for a run's grid world (started from ``init_from``'s parameters of matching
    shape when given); returns its size and training figures."""
    from rl.export import export_trainer
    from rl.gridmap import GridMap
    from rl.ppo import Trainer
    from rl.train_config import TrainConfig

    grid = GridMap.load(run_dir / GRID_FILE)
    trainer = Trainer(
        TrainConfig(map=grid.name, total_steps=steps, max_episode_steps=128, threads=1, init_from=str(init_from or "")),
        grid,
    )
    result = trainer.train()
    export_trainer(trainer, out, result.wall_s)
    return {"cells": f"{grid.shape[0]}x{grid.shape[1]}", "locations": grid.n_loops, "wall_s": result.wall_s}


def run_two_pass(spec: str, work: Path, steps: int, init_from: Path | None = None) -> list[dict[str, Any]]:
    first = work / "appearance"
    rows = [dict(run_one(spec, first), mode="appearance")]
    if not (first / GRID_FILE).is_file():
        return [*rows, {"dataset": spec, "mode": "policy", "skipped": "trajectory never crosses itself"}]
    policy = work / "policy.onnx"
    trained = train_policy(first, policy, steps, init_from)
    rows.append(
        dict(run_one(spec, work / "policy", {"source": "policy", "policy": str(policy)}), mode="policy", **trained)
    )
    # the front end is the same in both passes: its own trajectory is the "odometry only" row
    rows.append(dict(rows[0], mode="odometry only", accepted="-", false_accepted="-", windows="-", policy_p50_ms=None))
    return rows


def run_policy_loops_bench(
    console: Console, datasets: list[str] | None, steps: int, write: Path | None, init_from: Path | None = None
) -> list[dict[str, Any]]:
    results = []
    for spec in datasets or default_datasets():
        console.print(f"two-pass RL loop closure on {spec} ...")
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            results += run_two_pass(spec, Path(tmp), steps, init_from)
        console.print(f"  done in {time.perf_counter() - t0:.0f} s")
    header = [
        "dataset",
        "loop source",
        "grid (cells, locations)",
        "policy training",
        "accepted",
        "false accepted (target 0)",
        "revisit windows found",
        "ATE (cm)",
        "policy p50 per keyframe (ms)",
    ]
    rows = []
    start = f" from {init_from.stem}" if init_from else ""
    for r in results:
        name = Path(r["dataset"]).name if not r["dataset"].startswith("synthetic:") else r["dataset"]
        if "skipped" in r:
            rows.append([name, r["mode"], "-", r["skipped"], "-", "-", "-", "-", "-"])
            continue
        ate = r["ate_odometry_cm"] if r["mode"] == "odometry only" else r["ate_loops_cm"]
        rows.append(
            [
                name,
                r["mode"],
                f"{r['cells']}, {r['locations']}" if "cells" in r else "-",
                f"{steps} steps{start}, {r['wall_s']:.0f} s" if "wall_s" in r else "-",
                r["accepted"],
                r["false_accepted"],
                r["windows"],
                f"{ate:.2f}",
                f"{r['policy_p50_ms']:.2f}" if r.get("policy_p50_ms") is not None else "-",
            ]
        )
    show_table(console, "RL loop closure on real maps: policy vs appearance vs odometry only", header, rows)
    notes = (
        "Two passes per dataset: the appearance run builds the map and its grid world (0.25 m cells, "
        "crossings as loop-closure locations), a PPO policy is trained for it (128-step episodes, one "
        "thread; started from the shipped grid-world policy's parameters of matching shape when 'from' "
        "names one: its encoder and LSTM, and its heads when the location counts agree), then the policy "
        "is the only candidate source (a loop-closure action holds while the camera stays in its cell; "
        "the nearest earlier keyframes at the location are verified). A loop is false when the ground-truth "
        "poses of its frames are more than 0.3 m / 20 deg apart. 'policy p50' is the median time of "
        "projecting the pose, rendering the observation and running the ONNX policy, per keyframe."
    )
    record(
        "policy-loops",
        "RL loop closure in the service (issue 6)",
        f"objslam bench policy-loops --steps {steps}" + (f" --init-from {init_from}" if init_from else ""),
        markdown_table(header, rows),
        notes,
        write,
    )
    return results
