"""The map store's benchmarks (issue 27): checkpoint cost against map size, a long run, second sessions.

Registered on ``bench.commands.bench_app`` when that module is imported (it imports this one at its end)."""

from __future__ import annotations

from typing import Annotated

import typer

from bench.commands import WriteOpt, bench_app
from service.cli_common import UserError, console


@bench_app.command("persistence")
def bench_persistence(
    dataset: Annotated[
        str, typer.Option("--dataset", help="dataset spec")
    ] = "synthetic:room?seed=0&frames=800&fps=10&revolutions=4.5",
    keyframes: Annotated[str, typer.Option("--keyframes", help="checkpoints, comma separated")] = "100,200,300",
    write: WriteOpt = None,
) -> None:
    """Map store checkpoint / load / restore time and size against the number of keyframes."""
    from bench.persistence import run_persistence_bench

    try:
        checkpoints = [int(k) for k in keyframes.split(",")]
    except ValueError:
        raise UserError(f"--keyframes must be integers separated by commas, got {keyframes!r}") from None
    run_persistence_bench(console, dataset, checkpoints, write)


LONGRUN_DATASET = "synthetic:room?seed=0&frames=1100&revolutions=10&width=160&height=120&fps=10"
LONGRUN_ROWS = "1000,2000,5000,10000,20000"


@bench_app.command("longrun")
def bench_longrun(
    keyframes: Annotated[int, typer.Option("--keyframes", help="target number of keyframes")] = 20_000,
    checkpoints: Annotated[str, typer.Option("--checkpoints", help="rows at these keyframes")] = LONGRUN_ROWS,
    dataset: Annotated[str, typer.Option("--dataset", help="dataset spec, replayed over and over")] = LONGRUN_DATASET,
    minutes: Annotated[float | None, typer.Option("--minutes", help="stop after this wall time (a row there)")] = None,
    write: WriteOpt = None,
) -> None:
    """Map store cost, RSS and restart time against keyframes over a long synthetic run (issue 27)."""
    from bench.longrun import parse_rows, run_longrun_bench

    try:
        rows = parse_rows(checkpoints, keyframes, minutes)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    run_longrun_bench(console, dataset, keyframes, rows, minutes, write)


@bench_app.command("sessions")
def bench_sessions(write: WriteOpt = None) -> None:
    """Second sessions on a stored map from random places: frames until relocalized, false relocalizations, ATE
    in the first session's frame (issue 27)."""
    from bench.sessions import run_sessions_bench

    run_sessions_bench(console, write)
