"""``objslam calibrate reference``: print (and optionally record) how well a dataset's reference trajectory
agrees with its own depth, step by step and at a run's loop closures."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from rich.console import Console

from bench.calibrate import LoopCheck, ReferenceReport, check_loops, check_reference
from bench.report import markdown_table, record, show_table
from evaluation.reference_check import PairCheck
from graph.geometry import motion_magnitude
from sources import Dataset, truth_per_frame


def _mm(x: float) -> str:
    return f"{x * 1000:.1f}"


def _step(T: np.ndarray | None) -> str:
    if T is None:
        return "n/a"
    t, r = motion_magnitude(T)
    return f"{t * 1000:.1f} mm / {np.degrees(r):.2f} deg"


def summary_rows(report: ReferenceReport) -> list[list[object]]:
    """One row of medians over every checked pair."""
    c = [k for k in report.checks if k.T_depth is not None]
    med = lambda f: float(np.nanmedian([f(k) for k in c])) if c else float("nan")
    cost = (
        f"{report.repair_ate_m * 100:.2f}"
        if report.repair_ate_m is not None
        else "n/a (needs gap 1, stride 1, >= 3 frames)"
    )
    return [
        [
            len(report.checks),
            len(report.checks) - len(c),
            _mm(med(lambda k: k.displacement_m)),
            f"{med(lambda k: k.displacement_deg):.2f}",
            _mm(med(lambda k: k.residual_ref_m)),
            _mm(med(lambda k: k.residual_depth_m)),
            len(report.refuted_steps),
            sum(k.worse_than_still for k in report.checks if k.refuted(report.margin_m)),
            cost,
        ]
    ]


SUMMARY_HEADER = [
    "pairs",
    "ICP failed",
    "median depth optimum - reference (mm)",
    "(deg)",
    "median residual at reference (mm)",
    "at depth optimum (mm)",
    "refuted",
    "of them worse than no motion",
    "ATE of the repaired reference against the original (cm)",
]
REFUTED_HEADER = [
    "frames",
    "reference motion",
    "depth optimum",
    "residual at reference (mm)",
    "at depth optimum (mm)",
    "with no motion (mm)",
]
LOOP_HEADER = [
    "loop (match <- query)",
    "depth optimum - reference",
    "residual at reference (mm)",
    "at depth optimum (mm)",
    "at the loop's verified pose (mm)",
]


def refuted_rows(report: ReferenceReport) -> list[list[str]]:
    return [
        [
            f"{k.src} -> {k.dst}",
            _step(k.T_ref),
            _step(k.T_depth),
            _mm(k.residual_ref_m),
            _mm(k.residual_depth_m),
            _mm(k.residual_still_m),
        ]
        for k in report.checks
        if k.refuted(report.margin_m)
    ]


def loop_rows(loops: list[LoopCheck]) -> list[list[str]]:
    rows = []
    for lc in loops:
        k: PairCheck = lc.check
        rows.append(
            [
                f"{k.dst} <- {k.src}",
                f"{k.displacement_m * 100:.1f} cm / {k.displacement_deg:.2f} deg",
                _mm(k.residual_ref_m),
                _mm(k.residual_depth_m),
                _mm(lc.residual_loop_m),
            ]
        )
    if loops:
        col = lambda f: float(np.nanmedian([f(lc) for lc in loops]))
        rows.append(
            [
                "median",
                f"{col(lambda lc: lc.check.displacement_m) * 100:.1f} cm / "
                f"{col(lambda lc: lc.check.displacement_deg):.2f} deg",
                _mm(col(lambda lc: lc.check.residual_ref_m)),
                _mm(col(lambda lc: lc.check.residual_depth_m)),
                _mm(col(lambda lc: lc.residual_loop_m)),
            ]
        )
    return rows


def report_reference(
    console: Console,
    dataset: Dataset,
    spec: str,
    start: int,
    stop: int | None,
    gap: int,
    stride: int,
    margin_m: float,
    run_dir: Path | None,
    write: Path | None,
    options: str = "",
) -> ReferenceReport:
    """Check, print, and (with ``write``) record the reference-check section of the benchmarks file.
    ``options`` are the command-line options to record beside the command."""
    reference = truth_per_frame(dataset)
    records = json.loads((run_dir / "loops.json").read_text()) if run_dir is not None else None  # fail early
    report = check_reference(dataset, start, stop, gap, stride, margin_m, reference)
    title = f"reference against depth: {Path(spec).name if not spec.startswith('synthetic:') else spec}"
    show_table(console, title, SUMMARY_HEADER, summary_rows(report))
    show_table(
        console, f"steps the depth refutes (margin {margin_m * 1000:g} mm)", REFUTED_HEADER, refuted_rows(report)
    )
    loops = []
    if records is not None:
        loops = check_loops(dataset, records, reference)
        show_table(console, f"accepted loops of {run_dir}", LOOP_HEADER, loop_rows(loops))
    if write is not None:
        command = f"objslam calibrate reference {spec}{options}" + (" --loops RUN" if run_dir else "")
        table = (
            markdown_table(SUMMARY_HEADER, summary_rows(report))
            + "\n\n"
            + markdown_table(REFUTED_HEADER, refuted_rows(report))
        )
        if loops:
            table += "\n\n" + markdown_table(LOOP_HEADER, loop_rows(loops))
        record("reference", "The reference trajectory against its own depth", command, table, NOTES, write)
    return report


NOTES = (
    "For each frame pair, the depth of one frame is moved into the other by the reference's relative pose "
    "and compared with the other's depth (median |depth difference| over the pixels both see); the same for "
    "the motion the depth prefers (coarse-to-fine point-to-plane ICP started at the reference motion) and for "
    "no motion. A step is refuted when the reference's residual exceeds the depth optimum's by more than the "
    "margin. The repaired reference replaces each refuted step by the depth's motion; its ATE against the "
    "original is what those steps alone cost an estimate that follows the depth. With `--loops RUN`, the "
    "same for the run's accepted loop closures, and the residual of the loop's own verified pose. "
    "RUN is `objslam run DATASET --out RUN`."
)
