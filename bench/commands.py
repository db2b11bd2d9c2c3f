"""The ``objslam bench`` and ``objslam calibrate`` commands (developer tools; each bench prints a table and
can append it to docs/benchmarks.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from service.cli_common import UserError, console
from service.cli_common import camera_overrides as _camera_overrides


def register(app: typer.Typer) -> None:
    """Add ``calibrate`` and ``bench`` to the ``objslam`` application."""
    app.add_typer(calibrate_app, name="calibrate")
    app.add_typer(bench_app, name="bench")


calibrate_app = typer.Typer(
    help="Sensor calibration against a dataset's reference trajectory, and the reference checked against the sensor."
)


@calibrate_app.command("depth-scale")
def calibrate_depth_scale_cmd(
    dataset: Annotated[str, typer.Argument(help="directory or synthetic:NAME?... with ground truth")],
    start: Annotated[int, typer.Option("--start", help="first frame of the pairs")] = 0,
    stop: Annotated[int | None, typer.Option("--stop", help="frames before this one (default: all)")] = None,
    gap: Annotated[int, typer.Option("--gap", help="frames between the two of a pair")] = 15,
    stride: Annotated[int, typer.Option("--stride", help="a pair every N frames")] = 3,
    depth_scale: Annotated[float | None, typer.Option("--depth-scale", help="nominal units per metre")] = None,
) -> None:
    """The depth sensor's scale against the ground truth: depth ICP between frame pairs, started at the
    reference motion, against that motion. Prints the calibrated depth units per metre (for --depth-scale or
    camera.json's depth_scale)."""
    from bench.calibrate import calibrate_depth_scale
    from sources import open_dataset

    data = open_dataset(dataset, _camera_overrides(depth_scale=depth_scale))
    try:
        estimate = calibrate_depth_scale(data, start, stop, gap, stride)
    except ValueError as exc:
        raise UserError(f"{dataset}: {exc}") from None
    nominal = data.camera.depth_scale
    console.print(
        f"pairs {estimate.pairs} ({gap} frames apart); depth ICP / reference translation: median "
        f"{estimate.ratio:.4f}, quartiles {estimate.q25:.4f} .. {estimate.q75:.4f}"
    )
    console.print(
        f"depth units per metre: nominal {nominal:g}, calibrated {estimate.calibrated_depth_scale(nominal):.1f}"
    )


@calibrate_app.command("reference")
def calibrate_reference_cmd(
    dataset: Annotated[str, typer.Argument(help="directory or synthetic:NAME?... with ground truth")],
    start: Annotated[int, typer.Option("--start", help="first frame of the pairs")] = 0,
    stop: Annotated[int | None, typer.Option("--stop", help="frames before this one (default: all)")] = None,
    gap: Annotated[int, typer.Option("--gap", help="frames between the two of a pair")] = 1,
    stride: Annotated[int, typer.Option("--stride", help="a pair every N frames")] = 1,
    margin_mm: Annotated[
        float,
        typer.Option(
            "--margin-mm", help="refuted: the reference's depth residual exceeds the depth optimum's by more than this"
        ),
    ] = 5.0,
    loops: Annotated[
        Path | None, typer.Option("--loops", help="a run directory: check its accepted loops (loops.json) too")
    ] = None,
    depth_scale: Annotated[float | None, typer.Option("--depth-scale", help="nominal units per metre")] = None,
    write: Annotated[Path | None, typer.Option("--write", help="benchmarks markdown file")] = None,
) -> None:
    """The reference trajectory checked against the dataset's own depth: for frame pairs, the depth residual of
    the reference motion, of the motion the depth prefers (ICP started at the reference) and of no motion.
    Lists the steps the depth refutes and, for consecutive frames, what they alone cost in ATE."""
    from bench.reference_report import report_reference
    from sources import open_dataset

    data = open_dataset(dataset, _camera_overrides(depth_scale=depth_scale))
    try:
        options = "".join(
            f" --{name} {value:g}"
            for name, value, default in (
                ("start", start, 0),
                ("stop", stop, None),
                ("gap", gap, 1),
                ("stride", stride, 1),
                ("margin-mm", margin_mm, 5.0),
                ("depth-scale", depth_scale, None),
            )
            if value != default
        )
        report_reference(console, data, dataset, start, stop, gap, stride, margin_mm / 1000.0, loops, write, options)
    except (ValueError, OSError) as exc:
        raise UserError(f"{dataset}: {exc}") from None


bench_app = typer.Typer(help="Benchmarks: each prints a table and appends it to docs/benchmarks.md.")


@bench_app.command("throughput")
def bench_throughput(
    frames: Annotated[int, typer.Option("--frames")] = 300,
    dataset: Annotated[str, typer.Option("--dataset")] = "synthetic:room?seed=0",
    write: Annotated[Path | None, typer.Option("--write", help="benchmarks markdown file")] = None,
    ros2: Annotated[
        bool, typer.Option("--ros2", help="the ROS 2 ingest path (rmw_zenoh keys) against protocol v1")
    ] = False,
    rerun: Annotated[bool, typer.Option("--rerun", help="the viewer's cost: a Rerun recording on and off")] = False,
) -> None:
    """Replay-to-graph throughput at max rate over zenoh (frames pre-encoded, service in a subprocess)."""
    if rerun:
        from bench.viewer_throughput import run_viewer_throughput

        run_viewer_throughput(console, dataset, frames, write)
        return
    if ros2:
        from bench.ros2_throughput import run_ros2_throughput

        run_ros2_throughput(console, dataset, frames, write)
        return
    from bench.throughput import run_throughput

    run_throughput(console, dataset, frames, write)


@bench_app.command("isam2")
def bench_isam2(
    poses: Annotated[int, typer.Option("--poses")] = 10_000,
    landmarks: Annotated[int, typer.Option("--landmarks")] = 300,
    seed: Annotated[int, typer.Option("--seed")] = 0,
    write: Annotated[Path | None, typer.Option("--write", help="benchmarks markdown file")] = None,
) -> None:
    """iSAM2 update cost on a simulated exploration: odometry, loop closures, landmark observations."""
    from bench.isam2 import run_isam2_bench

    if poses < 20 or landmarks < 1:
        raise UserError("--poses must be at least 20 and --landmarks at least 1")
    run_isam2_bench(console, poses, landmarks, seed, write)


@bench_app.command("overload")
def bench_overload(
    seconds: Annotated[float, typer.Option("--seconds", help="overload duration")] = 60.0,
    factor: Annotated[float, typer.Option("--factor", help="publish rate / processing rate")] = 3.0,
    frames: Annotated[
        int | None, typer.Option("--frames", help="instead: a paced run of N frames (none dropped) for RSS growth")
    ] = None,
    dataset: Annotated[str, typer.Option("--dataset")] = "synthetic:room?seed=0",
    write: Annotated[Path | None, typer.Option("--write", help="benchmarks markdown file")] = None,
) -> None:
    """Publish faster than serve processes: bounded memory, counted drops, status latency under load."""
    from bench.overload import run_overload

    if seconds <= 0 or factor <= 0 or (frames is not None and frames <= 0):
        raise UserError("--seconds, --factor and --frames must be positive")
    run_overload(console, dataset, seconds, frames, factor, write)


@bench_app.command("hostile")
def bench_hostile(
    attacks: Annotated[
        str | None,
        typer.Option(
            "--attacks",
            help="comma separated subset (default all, in order): quiet, jpeg_bomb, "
            "png_bomb, garbage_flood, junk_60mb, label_flood, query_flood, save_flood, time_poison",
        ),
    ] = None,
    seconds: Annotated[
        float, typer.Option("--seconds", help="duration of quiet, the bombs and the garbage flood (junk: a third)")
    ] = 30.0,
    write: Annotated[bool, typer.Option("--write/--no-write", help="record the table in docs/benchmarks.md")] = True,
) -> None:
    """Crafted frames, floods and poisoned streams against serve (issue 26): memory, frames lost, recovery."""
    from bench.hostile import ATTACKS, run_hostile

    chosen = [a.strip() for a in attacks.split(",") if a.strip()] if attacks else list(ATTACKS)
    if unknown := sorted(set(chosen) - set(ATTACKS)):
        raise UserError(f"--attacks: unknown {', '.join(unknown)} (known: {', '.join(ATTACKS)})")
    if seconds < 3:
        raise UserError("--seconds must be at least 3 (a bomb every 3 s)")
    run_hostile(console, chosen, seconds, write)


DatasetsOpt = Annotated[list[str] | None, typer.Option("--dataset", help="dataset spec (repeatable)")]
WriteOpt = Annotated[Path | None, typer.Option("--write", help="benchmarks markdown file")]


@bench_app.command("odometry")
def bench_odometry(dataset: DatasetsOpt = None, write: WriteOpt = None) -> None:
    """ATE/RPE of the RGB-D front end with and without loops (7-Scenes + 3 synthetic seeds); also loop table."""
    from bench.slam import run_slam_bench

    run_slam_bench(console, dataset, write)


@bench_app.command("robustness")
def bench_robustness(
    seeds: Annotated[str | None, typer.Option("--seeds", help="synthetic seeds (default: the held-out ones)")] = None,
    write: WriteOpt = None,
) -> None:
    """Tracking on 7-Scenes every 20th / 30th / 45th frame and with 30 % / 60 % of frames dropped, and on
    synthetic scenes with a blank wall and a 30-frame gap: ATE, losses, invented poses, segments."""
    from bench.robustness import run_robustness_bench

    run_robustness_bench(console, write, _seeds(seeds) if seeds else None)


@bench_app.command("loops")
def bench_loops(dataset: DatasetsOpt = None, write: WriteOpt = None) -> None:
    """Loop candidates judged against ground truth (same runs as `bench odometry`, both tables recorded)."""
    from bench.slam import run_slam_bench

    run_slam_bench(console, dataset, write)


SeedsOpt = Annotated[str, typer.Option("--seeds", help="synthetic seeds, comma separated")]


@bench_app.command("landmarks")
def bench_landmarks(dataset: DatasetsOpt = None, write: WriteOpt = None) -> None:
    """Objects in the graph: ATE with and without object landmarks and loop closures, landmark errors."""
    from bench.landmarks import run_landmarks_bench

    run_landmarks_bench(console, dataset, write)


@bench_app.command("policy-loops")
def bench_policy_loops(
    dataset: DatasetsOpt = None,
    steps: Annotated[int, typer.Option("--steps", help="policy training steps per map")] = 100_000,
    init_from: Annotated[
        str,
        typer.Option(
            "--init-from",
            help="checkpoint (.pt) that starts each policy; default: the config1 policy "
            "before memory pretraining, models/lc/config1.init.pt ('' = from scratch)",
        ),
    ] = "config1",
    write: WriteOpt = None,
) -> None:
    """Two passes per dataset: map + grid world, train a policy, re-run with policy loop closures."""
    from bench.policy_loops import run_policy_loops_bench
    from rl.commands import INIT_CHECKPOINT, POLICY_DIR

    start = POLICY_DIR / INIT_CHECKPOINT if init_from == "config1" else Path(init_from) if init_from else None
    run_policy_loops_bench(console, dataset, steps, write, start)


@bench_app.command("lc-batch")
def bench_lc_batch(
    grid: Annotated[str, typer.Option("--map", help="grid configuration")] = "config2",
    steps: Annotated[int, typer.Option("--steps", help="training steps per variant")] = 40_000,
    plot: Annotated[Path, typer.Option("--plot", help="reward-curve PNG")] = Path("docs/lc_batch_ablation.png"),
    write: WriteOpt = None,
) -> None:
    """Fig. 3.10: fixed 512, fixed 2048 and entropy-based batch sizes, reward curves and evaluation."""
    from bench.lc_ablation import run_batch_ablation

    run_batch_ablation(console, grid, steps, plot, write)


def _seeds(text: str) -> list[int]:
    try:
        return [int(s) for s in text.replace(",", " ").split()]
    except ValueError:
        raise UserError(f"--seeds must be integers separated by commas, got {text!r}") from None


@bench_app.command("association")
def bench_association(
    seeds: Annotated[
        str | None,
        typer.Option("--seeds", help="synthetic seeds, comma separated (default 0,1,2; --family: the held-out seeds)"),
    ] = None,
    frames: Annotated[
        int | None, typer.Option("--frames", help="frames per scene (default 300; --family: 900)")
    ] = None,
    write: WriteOpt = None,
    family: Annotated[
        bool,
        typer.Option("--family", help="consecutive keyframes of the held-out scene family, by assignment rule"),
    ] = False,
) -> None:
    """NPDA precision/recall on synthetic keyframes, the Table 2.2 grid, ablation and timing (--family: on the
    held-out scene family's keyframes, with the swaps between same-class neighbours, per assignment rule)."""
    if family:
        from bench.association_family import run_association_family
        from bench.objects_family import FAMILY_FRAMES, family_seeds

        chosen = family_seeds(seeds)
        run_association_family(console, chosen, frames or FAMILY_FRAMES, write)
        return
    from bench.association import run_association_bench

    run_association_bench(console, _seeds(seeds or "0,1,2"), frames or 300, write)


@bench_app.command("objects")
def bench_objects(
    seeds: Annotated[
        str | None,
        typer.Option(
            "--seeds",
            help="synthetic seeds, comma separated (default 0,1,2; --family: the held-out seeds, "
            "'dev' the development seeds)",
        ),
    ] = None,
    frames: Annotated[
        int | None, typer.Option("--frames", help="frames per scene (default 300; --family: 900)")
    ] = None,
    family: Annotated[
        bool, typer.Option("--family", help="the randomized scene family (synthetic:family) instead of the room")
    ] = False,
    detector_errors: Annotated[
        bool,
        typer.Option(
            "--detector-errors",
            help="with --family: the scenes again under each simulated detector error (wobbling boxes, confused "
            "labels, part boxes, all)",
        ),
    ] = False,
    write: WriteOpt = None,
) -> None:
    """Objects mapped / present, false objects, ground-plane IoU and centroid error on synthetic scenes (--family:
    median and worst decile over the held-out family scenes, IoU by size class, row neighbours by spacing; the
    table is recorded only with --write)."""
    if frames is not None and frames < 2:
        raise UserError("--frames must be at least 2")
    if detector_errors and not family:
        raise UserError("--detector-errors needs --family")
    if family:
        from bench.objects_family import FAMILY_FRAMES, family_seeds, run_family_bench

        try:
            chosen = family_seeds(seeds)
        except ValueError:
            raise UserError(
                f"--seeds must be integers separated by commas, 'dev' or 'held-out', got {seeds!r}"
            ) from None
        if detector_errors:
            from bench.objects_family_errors import run_error_sweep

            run_error_sweep(console, chosen, frames or FAMILY_FRAMES, write)
            return
        run_family_bench(console, chosen, frames or FAMILY_FRAMES, write)
        return
    from bench.objects import run_objects_bench

    run_objects_bench(console, _seeds(seeds or "0,1,2"), frames or 300, write)


@bench_app.command("stages")
def bench_stages(
    dataset: Annotated[str, typer.Option("--dataset", help="dataset spec")],
    frames: Annotated[int | None, typer.Option("--frames")] = None,
    write: WriteOpt = None,
) -> None:
    """Per-stage latency of the whole pipeline; keyframes/s of detection + association."""
    from bench.stages import run_stages_bench

    run_stages_bench(console, dataset, frames, write)


@bench_app.command("frontends")
def bench_frontends(
    dataset: Annotated[str, typer.Option("--dataset", help="dataset with ground truth")],
    frames: Annotated[int, typer.Option("--frames")] = 400,
    write: WriteOpt = None,
) -> None:
    """Compare odometry front-end candidates (ORB, ORB + ICP, SIFT) on a real segment."""
    from bench.frontends import run_frontends_bench

    run_frontends_bench(console, dataset, frames, write)


@bench_app.command("detector")
def bench_detector(
    dataset: Annotated[str, typer.Option("--dataset", help="dataset directory")],
    every: Annotated[int, typer.Option("--every", help="every N-th frame")] = 10,
    write: WriteOpt = None,
) -> None:
    """Detector speed and detections per class on real frames; saves contact sheets in docs/."""
    from bench.detector import run_detector_bench

    run_detector_bench(console, dataset, every, write)


from bench import commands_detector, commands_live, commands_store  # noqa: E402, F401  (their commands register on bench_app)
