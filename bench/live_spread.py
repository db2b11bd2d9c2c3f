"""``objslam bench live-spread``: the live service's ATE against the offline run's as the keyframe rule moves a
little (issue 28).

Which frames become keyframes decides the graph, its loop closures and so the ATE. ``serve --live`` decides them
while tracking goes on (keyframes are made beside it), so its keyframes are not those of ``objslam run``, which
takes every frame in order. How far the offline ATE itself moves when the rule moves a little (the translation or
the rotation threshold a step, 10 % by default, lower or higher; several steps give more rules) says how closely a
single live run can be held to a single offline one. Here both run under each rule: the same frames (bare, as in
``bench live``), offline first, then live at the camera rate into a ``serve`` subprocess, settled after the
stream, with each run's keyframes and accepted loop closures. The summary compares the medians, and gives the
median of the paired differences (live less offline under one rule) with its 95 % bootstrap interval.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console

from bench.live import (
    Published,
    _cm,
    _trajectory,
    first_frames,
    offline_ate_of,
    offline_summary,
    offline_summary_of,
    serve_live,
)
from bench.report import markdown_table, record, show_table
from evaluation.trajectory_metrics import evaluate
from perception.keyframing import KeyframeSettings
from service.protocol import encode_frame

STEP = 0.1
"""The keyframe rule's thresholds are moved by this share either way."""


def rules(*steps: float) -> dict[str, KeyframeSettings]:
    """The service's keyframe rule and, one at a time, its translation and rotation thresholds each of ``steps``
    (default ``STEP``) lower and higher."""
    base = KeyframeSettings()
    out = {"the service's rule": base}
    for step in steps or (STEP,):
        for field, unit in (("translation_m", "m"), ("rotation_deg", "deg")):
            for sign in (-1, 1):
                value = round(getattr(base, field) * (1 + sign * step), 6)
                out[f"{field} {value:g} {unit}"] = base.model_copy(update={field: value})
    return out


def env_of(rule: KeyframeSettings) -> dict[str, str]:
    """The environment that gives ``serve`` the keyframe rule ``rule`` (fields that differ from the default)."""
    base = KeyframeSettings()
    return {f"OBJSLAM_KEYFRAMES__{k.upper()}": str(v) for k, v in rule.model_dump().items() if v != getattr(base, k)}


def measure_spread(
    dataset: str, frames: int, rate_hz: float, steps: tuple[float, ...] = (STEP,)
) -> list[dict[str, Any]]:
    """Per keyframe rule: the offline ATE on the dataset's frames and on the frames as published (decoded from
    the live run's messages), and the live run's ATE at the stream's end and settled (m)."""
    bare = first_frames(dataset, frames)
    payloads = [encode_frame(bare.frame(i)) for i in range(len(bare))]
    published = Published(bare, payloads)
    out = []
    for name, rule in rules(*steps).items():
        summary = offline_summary(dataset, len(payloads), rule)
        same_pixels = offline_ate_of(offline_summary_of(published, rule))
        env = {"OBJSLAM_INGEST__LIVE": "true", **env_of(rule)}
        with tempfile.TemporaryDirectory() as state:
            status, reply, settled, _ = serve_live(payloads, rate_hz, {**env, "OBJSLAM_STATE_DIR": state}, settle=True)
        end = evaluate(_trajectory(reply), bare.ground_truth)
        calm = evaluate(_trajectory(settled), bare.ground_truth) if settled is not None else None
        out.append(
            {
                "rule": name,
                "offline": offline_ate_of(summary),
                "offline_published": same_pixels,
                "keyframes": (summary.get("keyframes"), status.get("keyframes")),
                "loops": (summary.get("loop_closures"), status.get("loop_closures", {}).get("accepted")),
                "live_end": end.ate_rmse_m if end is not None else None,
                "live_settled": calm.ate_rmse_m if calm is not None else None,
            }
        )
    return out


def _minus(a: float | None, b: float | None) -> float | None:
    return a - b if a is not None and b is not None else None


def _median(values: list[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return float(np.median(known)) if known else None


def spread_rows(dataset: str, results: list[dict[str, Any]]) -> list[list[str]]:
    """A row per rule, then the medians over the rules and the median of the rules' live - offline differences
    (paired: each live run against the offline run of its own rule), against the offline run on the dataset's
    frames and against the one on the frames as published."""
    diffs = [_minus(r["live_settled"], r["offline"]) for r in results]
    same = [_minus(r["live_settled"], r.get("offline_published")) for r in results]
    rows = [
        [
            f"`{dataset}`",
            r["rule"],
            _cm(r["offline"]),
            _cm(r["live_end"]),
            _cm(r["live_settled"]),
            _cm(d),
            _pair(r.get("keyframes")),
            _pair(r.get("loops")),
            _cm(r.get("offline_published")),
            _cm(e),
        ]
        for r, d, e in zip(results, diffs, same, strict=True)
    ]
    med = {
        k: _median([r.get(k) for r in results]) for k in ("offline", "live_end", "live_settled", "offline_published")
    }
    lower = sum(d is not None and d <= 0 for d in diffs)
    lower_same = sum(e is not None and e <= 0 for e in same)
    rows.append(
        [
            f"`{dataset}`",
            f"**median of {len(results)}** (live settled <= offline in {lower}; <= offline on the published frames "
            f"in {lower_same})",
            f"**{_cm(med['offline'])}**",
            _cm(med["live_end"]),
            f"**{_cm(med['live_settled'])}**",
            _cm(_minus(med["live_settled"], med["offline"])),
            "",
            "",
            f"**{_cm(med['offline_published'])}**",
            _cm(_minus(med["live_settled"], med["offline_published"])),
        ]
    )
    known = [[d for d in v if d is not None] for v in (diffs, same)]
    intervals = [median_interval(k) if k else (None, None) for k in known]
    rows.append(
        [
            f"`{dataset}`",
            f"**median of the {len(known[0])} differences** (95 % bootstrap interval {_cm(intervals[0][0])} to "
            f"{_cm(intervals[0][1])}; on the published frames {_cm(intervals[1][0])} to {_cm(intervals[1][1])})",
            "",
            "",
            "",
            f"**{_cm(_median(diffs))}**",
            "",
            "",
            "",
            f"**{_cm(_median(same))}**",
        ]
    )
    return rows


def _pair(values: tuple[Any, Any] | None) -> str:
    """``offline / live`` counts, ``-`` for one not known."""
    return " / ".join("-" if v is None else str(v) for v in (values or (None, None)))


def median_interval(values: list[float], draws: int = 20000, seed: int = 0) -> tuple[float, float]:
    """The 95 % bootstrap interval of the median of ``values`` (resampled with replacement, a fixed seed)."""
    samples = np.random.default_rng(seed).choice(np.asarray(values, float), (draws, len(values)))
    lo, hi = np.percentile(np.median(samples, axis=1), [2.5, 97.5])
    return float(lo), float(hi)


HEADER = [
    "dataset",
    "keyframe rule",
    "offline ATE (cm)",
    "live ATE at the end (cm)",
    "live ATE settled (cm)",
    "settled - offline (cm)",
    "keyframes offline / live",
    "loop closures offline / live",
    "offline ATE on the published frames (cm)",
    "settled - offline on the published frames (cm)",
]


def run_spread_bench(
    console: Console, datasets: list[str], frames: int, rate_hz: float, steps: list[float], write: Path | None
) -> list[dict[str, Any]]:
    results = {d: measure_spread(d, frames, rate_hz, tuple(steps)) for d in datasets}
    rows = [row for d, rs in results.items() for row in spread_rows(d, rs)]
    table = markdown_table(HEADER, rows)
    show_table(console, "live against offline as the keyframe rule moves", HEADER, rows)
    offline = [r["offline"] for rs in results.values() for r in rs if r["offline"] is not None]
    notes = (
        f"Each dataset's first {frames} frames, bare (no odometry, no detections), run offline (`objslam run`: "
        f"every frame in order) and live (`serve --live`, published at {rate_hz:g} Hz as in `bench live`) under "
        f"the service's keyframe rule and under that rule with its translation or rotation threshold "
        f"{' / '.join(f'{s:.0%}' for s in steps)} lower or higher (`keyframes.translation_m`, "
        "`keyframes.rotation_deg`). Live ATE settled: once the pause after the stream has moved the graph to its "
        "batch optimum (`ingest.polish_after_s`). The last row: the median over the rules of each live run's ATE "
        "less the offline run's of its own rule. The last two columns: the offline run again on the frames exactly as "
        "the live service decodes them (JPEG colour, PNG depth: `bench.live.Published`), so that the live run and it "
        "see the same pixels. Offline ATE over the rules: "
        f"{min(offline) * 100:.2f}-{max(offline) * 100:.2f} cm."
        if offline
        else ""
    )
    spec = " ".join(f"--dataset '{d}'" for d in datasets)
    path = record(
        "live-spread",
        "Live against offline as the keyframe rule moves",
        f"objslam bench live-spread {spec} --frames {frames} --rate {rate_hz:g} "
        + " ".join(f"--step {s:g}" for s in steps),
        table,
        notes,
        write,
    )
    console.print(f"recorded in {path}")
    return [r | {"dataset": d} for d, rs in results.items() for r in rs]
