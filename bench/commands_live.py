"""The camera-rate benchmark (issue 28): ``objslam bench live``.

Registered on ``bench.commands.bench_app`` when that module is imported (it imports this one at its end)."""

from __future__ import annotations

from typing import Annotated

import typer

from bench.commands import DatasetsOpt, WriteOpt, bench_app
from service.cli_common import console

FramesOpt = Annotated[int, typer.Option("--frames", help="frames of each dataset")]
RateOpt = Annotated[float, typer.Option("--rate", help="camera rate (frames/s)", min=1.0, max=1000.0)]
LIVE_DATASETS = ("../shared/data/7scenes_redkitchen_1000", "synthetic:family?seed=1001&frames=600")  # held out


@bench_app.command("live")
def bench_live(
    dataset: DatasetsOpt = None,
    frames: FramesOpt = 1000,
    rate: RateOpt = 30.0,
    profile: Annotated[
        bool, typer.Option("--profile", help="record serve with py-spy: its top costs per frame")
    ] = False,
    repeat: Annotated[int, typer.Option("--repeat", help="runs of the live configuration", min=1)] = 3,
    write: WriteOpt = None,
) -> None:
    """Datasets replayed at camera rate into `serve` (detector on, visual tracking), before issue 28's changes,
    with flow tracking, and live: frames posed, pose latency, mapping lag, drops by reason, ATE against the
    offline run."""
    from bench.live import run_live_bench

    run_live_bench(console, list(dataset or LIVE_DATASETS), frames, rate, profile, write, repeat)


@bench_app.command("live-spread")
def bench_live_spread(
    dataset: DatasetsOpt = None,
    frames: FramesOpt = 1000,
    rate: RateOpt = 30.0,
    step: Annotated[
        list[float] | None,
        typer.Option("--step", help="share by which each keyframe threshold moves (repeatable)", min=0.0, max=0.5),
    ] = None,
    write: WriteOpt = None,
) -> None:
    """Live against offline ATE under the service's keyframe rule and that rule with its translation or
    rotation threshold a step lower or higher: how closely one live run can be held to one offline run."""
    from bench.live_spread import run_spread_bench

    run_spread_bench(console, list(dataset or LIVE_DATASETS[:1]), frames, rate, list(step or [0.1]), write)
