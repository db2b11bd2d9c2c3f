"""The detector's box stability against the simulated detector's: ``objslam bench box-stability``.

Registered on ``bench.commands.bench_app`` when that module is imported (it imports this one at its end)."""

from __future__ import annotations

from typing import Annotated

import typer

from bench.commands import WriteOpt, bench_app
from service.cli_common import UserError, console


@bench_app.command("box-stability")
def bench_box_stability(
    dataset: Annotated[
        list[str] | None,
        typer.Option(
            "--dataset", help="dataset spec, repeatable (default: the two real sequences and two family scenes)"
        ),
    ] = None,
    start: Annotated[int, typer.Option("--start", help="first frame")] = 0,
    frames: Annotated[int, typer.Option("--frames", help="consecutive frames per source")] = 150,
    write: WriteOpt = None,
) -> None:
    """How much detector boxes move from frame to frame: the real detector on real frames against the simulated
    one, at its defaults and with the detector errors of bench objects --family --detector-errors."""
    from bench.box_stability import run_box_stability
    from bench.objects_family_errors import LEVELS

    if frames < 2 or start < 0:
        raise UserError("--frames must be at least 2 and --start at least 0")
    specs = dataset or [
        "../shared/data/7scenes_redkitchen_1000",
        "../shared/data/tum_fr3_teddy_200",
        "synthetic:family?seed=1001&frames=300",
        "synthetic:family?seed=1001&frames=300&" + LEVELS["all of these at half, 12 % missed"],
    ]
    run_box_stability(console, specs, start, frames, write)
