"""``objslam bench robustness``: tracking on wide baselines, dropped frames, blank walls and a gap.

Four tables, each run end to end through the service with the visual front end (frames without odometry) and
appearance loop closure:

1. 7-Scenes redkitchen at full rate and every 20th, 30th and 45th frame (15, 22 and 33 cm steps);
2. 7-Scenes at full rate with 30 % and 60 % of the frames dropped at random (seeded), against the full rate;
3. the ``synthetic:blank`` scene (plain walls and ceiling; for a stretch the camera sees nothing else) on
   held-out seeds: frames lost, left unposed or in segments never joined, and poses invented: frames in
   ``trajectory.tum`` more than 10 cm from the truth after alignment;
4. the synthetic room with 30 frames missing where the camera comes back to its start (a relocalization).

The synthetic seeds are held out: nothing was tuned on them (development used seeds 0-40). One held-out
failure was inspected (blank seed 1007: depth ICP alone jumped to a minimum 1.8 m away); its mechanism was
reproduced on development seeds 4, 33 and 35 and fixed there (``icp_max_travel_*``); seeds 1010-1019 were
added afterwards, unseen.
"""

from __future__ import annotations

import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console

from bench.report import markdown_table, record, show_table
from evaluation.trajectory_metrics import umeyama
from graph.trajectory import Trajectory, nearest_timestamps
from service.config import load_settings
from service.run import run_dataset
from sources import Dataset, Subset, WithoutOdometry, ground_truth_of, open_dataset
from sources.tum import read_trajectory

REDKITCHEN = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "7scenes_redkitchen_1000"
STRIDES = (1, 20, 30, 45)
STRIDE_TARGETS = {1: "<= 4.08 (today's full rate)", 20: "<= 5", 30: "<= 6", 45: "<= 10"}
DROPS = (0.3, 0.6)
DROP_SEEDS = (0, 1)
HELD_OUT = tuple(range(1000, 1020))
GAP_SEEDS = tuple(range(1000, 1010))
INVENTED_M = 0.10


def run(dataset: Dataset) -> dict[str, Any]:
    """One end-to-end run of ``dataset`` without odometry: its summary plus the poses it wrote."""
    settings = load_settings(None, {"loops": {"source": "appearance"}})
    with tempfile.TemporaryDirectory() as tmp:
        summary = run_dataset(WithoutOdometry(dataset), Path(tmp), settings, progress=False)
        summary["written"] = read_trajectory(Path(tmp) / "trajectory.tum")
    return summary


def invented(dataset: Dataset, written: Trajectory) -> int:
    """Frames of ``trajectory.tum`` farther than ``INVENTED_M`` from the truth after SE(3) alignment."""
    truth = ground_truth_of(dataset)
    match = nearest_timestamps(written.timestamps, truth.timestamps, 0.01)
    ok = match >= 0
    est, ref = written.poses[ok, :3, 3], truth.poses[match[ok], :3, 3]
    if len(est) < 3:
        return 0
    T = umeyama(est, ref)
    moved = est @ T[:3, :3].T + T[:3, 3]
    return int((np.linalg.norm(moved - ref, axis=1) > INVENTED_M).sum())


def _figures(summary: dict[str, Any]) -> dict[str, Any]:
    t = summary["tracking"]
    untied = sum(b - a + 1 for a, b in t["untied_frames"])
    return {
        "frames": summary["frames_processed"],
        "ate_odometry_cm": summary["ate"]["odometry"]["ate_rmse_m"] * 100,
        "ate_cm": summary["ate"]["trajectory"]["ate_rmse_m"] * 100,
        "posed": summary["ate"]["trajectory"]["pairs"],
        "lost": summary["tracking_lost"],
        "methods": ", ".join(f"{k} {v}" for k, v in sorted(t["methods"].items())),
        "segments": t["segments"],
        "joins": t["joins"],
        "unjoined": t["segments_unjoined"],
        "untied": untied,
        "loops": summary["loop_closures"],
    }


def stride_rows(console: Console) -> list[list[Any]]:
    rows = []
    for stride in STRIDES:
        console.print(f"7-Scenes every {stride}. frame ...")
        f = _figures(run(Subset.strided(open_dataset(str(REDKITCHEN)), stride)))
        rows.append(
            [
                stride,
                f["frames"],
                f"{f['ate_odometry_cm']:.2f}",
                f"{f['ate_cm']:.2f}",
                STRIDE_TARGETS[stride],
                f["lost"],
                f["methods"],
                f"{f['segments']} / {f['joins']} / {f['unjoined']}",
                f["untied"],
                f["loops"],
            ]
        )
    return rows


def drop_rows(console: Console, full_ate_cm: float) -> list[list[Any]]:
    rows = []
    for drop in DROPS:
        for seed in DROP_SEEDS:
            console.print(f"7-Scenes with {drop:.0%} dropped (seed {seed}) ...")
            f = _figures(run(Subset.dropped(open_dataset(str(REDKITCHEN)), drop, seed)))
            rows.append(
                [
                    f"{drop:.0%}",
                    seed,
                    f["frames"],
                    f"{f['ate_cm']:.2f}",
                    f"{f['ate_cm'] - full_ate_cm:+.2f}",
                    "within +-1 cm of full rate",
                    f["lost"],
                    f["methods"],
                    f["untied"],
                ]
            )
    return rows


def synthetic_rows(console: Console, scene: str, seeds: Sequence[int]) -> tuple[list[list[Any]], list[dict]]:
    rows, figures = [], []
    for seed in seeds:
        console.print(f"synthetic:{scene} seed {seed} ...")
        data: Dataset = open_dataset(f"synthetic:{scene}?seed={seed}&frames=300")
        if scene == "room":  # 30 frames missing where the camera comes back to where it started
            data = Subset(data, np.r_[0:240, 270:300], "gap 240-269")
        summary = run(data)
        f = {**_figures(summary), "invented": invented(data, summary["written"]), "seed": seed}
        figures.append(f)
        rows.append(
            [
                seed,
                f["frames"],
                f"{f['ate_cm']:.2f}",
                f["posed"],
                f["lost"],
                f["invented"],
                f["methods"],
                f"{f['segments']} / {f['joins']} / {f['unjoined']}",
                f["untied"],
            ]
        )
    return rows, figures


def summary_row(name: str, figures: list[dict]) -> list[Any]:
    """Median and worst decile (90th percentile) of ATE, invented poses and unjoined segments."""
    ate, unjoined = [f["ate_cm"] for f in figures], [f["unjoined"] for f in figures]
    return [
        name,
        len(figures),
        f"{np.median(ate):.2f} / {np.percentile(ate, 90):.2f}",
        f"{sum(f['invented'] for f in figures)} (target 0)",
        f"{np.median(unjoined):.0f} / {np.percentile(unjoined, 90):.0f}",
        sum(f["lost"] for f in figures),
        sum(f["untied"] for f in figures),
    ]


def run_robustness_bench(console: Console, write: Path | None, seeds: Sequence[int] | None = None) -> None:
    """Run the four cases; print and record their tables."""
    synthetic_header = [
        "seed",
        "frames",
        "ATE with loops (cm)",
        "frames posed",
        "frames lost",
        "poses invented (> 10 cm)",
        "method (frames)",
        "segments / joins / unjoined",
        "frames not in the map",
    ]
    blank, blank_figures = synthetic_rows(console, "blank", seeds or HELD_OUT)
    gap, gap_figures = synthetic_rows(console, "room", GAP_SEEDS if seeds is None else seeds)
    summary_header = [
        "case",
        "seeds",
        "ATE median / worst decile (cm)",
        "poses invented",
        "unjoined segments median / worst decile",
        "frames lost",
        "frames not in the map",
    ]
    summary = [summary_row("blank wall", blank_figures), summary_row("30-frame gap", gap_figures)]
    tables = [("texture-poor and gap cases: summary", summary_header, summary)]
    tables += [("synthetic:blank (held-out seeds)", synthetic_header, blank)]
    tables += [("synthetic:room, frames 240-269 missing (held-out seeds)", synthetic_header, gap)]
    if REDKITCHEN.is_dir():
        strides = stride_rows(console)
        stride_header = [
            "stride",
            "frames",
            "ATE odometry only (cm)",
            "ATE with loops (cm)",
            "target (cm)",
            "frames lost",
            "method (frames)",
            "segments / joins / unjoined",
            "frames not in the map",
            "loops accepted",
        ]
        full = float(strides[0][3])
        drops = drop_rows(console, full)
        drop_header = [
            "dropped",
            "seed",
            "frames",
            "ATE with loops (cm)",
            "vs full rate (cm)",
            "target",
            "frames lost",
            "method (frames)",
            "frames not in the map",
        ]
        tables = [
            ("7-Scenes redkitchen subsampled", stride_header, strides),
            ("7-Scenes redkitchen with frames dropped at random", drop_header, drops),
            *tables,
        ]
    text = []
    for title, header, rows in tables:
        show_table(console, title, header, rows)
        text.append(f"**{title}**\n\n{markdown_table(header, rows)}")
    if write is not None:
        notes = (
            "Every run replays the frames without odometry through the service (embedded zenoh, appearance loop "
            "closure). ATE is RMSE after SE(3) alignment over the frames in `trajectory.tum`, which holds only "
            "frames tied to the map ('frames posed'); 'frames not in the map' are the rest: lost with nothing "
            "to track from, or in a segment that nothing joined. 'Poses invented': frames of `trajectory.tum` "
            f"more than {INVENTED_M * 100:.0f} cm from the truth after alignment. Methods: how each frame was "
            "posed (features, wide-baseline features, guided matching, depth ICP, relocalized, lost). "
            "Segments: started by a loss (the first one included) / joins by relocalization or loop closure / "
            "left unjoined. The synthetic seeds are held out (development used blank seeds 0-40). Blank seed 1007's "
            "failure in the first run (ICP alone jumped to a minimum 1.8 m away: 286 poses invented) was inspected, "
            "reproduced on development seeds 4, 33 and 35 and fixed there (`odometry.icp_max_travel_m` / `_deg`); "
            "seeds 1010-1019 were added after that, unseen."
        )
        record(
            "robustness",
            "Tracking robustness: strides, drops, blank walls, gaps",
            "objslam bench robustness",
            "\n\n".join(text),
            notes,
            write,
        )
