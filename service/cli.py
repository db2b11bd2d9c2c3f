"""The ``objslam`` command line: serve, replay, status, run, eval, config, calibrate, bench."""

from __future__ import annotations

import json
import logging
import sys
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.text import Text

from bench import commands as bench_commands
from rl import commands as lc_cli
from service.cli_common import UserError, console, positive_finite
from service.cli_common import camera_overrides as _camera_overrides
from service.cli_ros2 import (
    DepthTopicOpt,
    DetectionsTopicOpt,
    DomainOpt,
    InfoTopicOpt,
    OdomTopicOpt,
    RgbTopicOpt,
    Ros2Opt,
    is_rosbag,
    ros2_overrides,
    ros_topics,
)
from service.config import ConfigError, Settings, dump_defaults, load_settings
from service.viewer_cli import NoRrdOpt, RerunOpt, RerunWebOpt, RrdOpt, viewer_overrides
from sources import DatasetError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="objslam: semantic SLAM backend over zenoh (object association, iSAM2, RL loop closure).",
)

ConfigOpt = Annotated[Path | None, typer.Option("--config", help="YAML configuration file")]
RobotOpt = Annotated[str | None, typer.Option("--robot", help="robot name: keys are <key_prefix>/<robot>/...")]
ConnectOpt = Annotated[list[str] | None, typer.Option("--connect", help="zenoh endpoint to connect to")]
ListenOpt = Annotated[list[str] | None, typer.Option("--listen", help="zenoh endpoint to listen on")]
ModeOpt = Annotated[str | None, typer.Option("--mode", help="zenoh mode: peer, client or router")]
ZenohConfigOpt = Annotated[
    Path | None,
    typer.Option("--zenoh-config", help="native zenoh configuration file (TLS, authentication, access control)"),
]


class LcSource(StrEnum):
    off = "off"
    appearance = "appearance"
    policy = "policy"
    both = "both"


class QueryKind(StrEnum):
    status = "status"
    objects = "objects"
    trajectory = "trajectory"
    loops = "loops"


def _settings(
    config: Path | None,
    robot: str | None = None,
    connect: list[str] | None = None,
    listen: list[str] | None = None,
    mode: str | None = None,
    state_dir: Path | None = None,
    zenoh_config: Path | None = None,
    extra: dict[str, Any] | None = None,
) -> Settings:
    overrides: dict[str, Any] = dict(extra or {})
    zenoh_over: dict[str, Any] = {}
    if robot:
        overrides["robot"] = robot
    if state_dir:
        overrides["state_dir"] = state_dir
    if connect:
        zenoh_over["connect"] = connect
    if listen:
        zenoh_over["listen"] = listen
    if mode:
        zenoh_over["mode"] = mode
    if zenoh_config:
        zenoh_over["config_file"] = zenoh_config
    if zenoh_over:
        overrides["zenoh"] = zenoh_over
    return load_settings(config, overrides)


def _with_lc(settings: Settings, lc_source: LcSource | None, lc_policy: Path | None) -> Settings:
    """Apply ``--lc-source`` and ``--lc-policy``; the policy sources need a policy file."""
    source = lc_source.value if lc_source is not None else settings.loops.source
    policy = settings.loops.policy
    if lc_policy is not None:
        if not lc_policy.is_file() or not lc_policy.with_suffix(".json").is_file():
            raise UserError(f"--lc-policy {lc_policy}: needs FILE.onnx and FILE.json (from train-lc)")
        policy = lc_policy
    if source in ("policy", "both") and policy is None:
        raise UserError(f"--lc-source {source} needs --lc-policy FILE.onnx (train one with train-lc --from-map)")
    settings.loops = settings.loops.model_copy(update={"source": source, "policy": policy})
    return settings


@app.command()
def serve(
    config: ConfigOpt = None,
    robot: RobotOpt = None,
    connect: ConnectOpt = None,
    listen: ListenOpt = None,
    mode: ModeOpt = None,
    state_dir: Annotated[
        Path | None, typer.Option("--state-dir", help="snapshots (resumed from on start) and, on shutdown, the outputs")
    ] = None,
    lc_source: Annotated[LcSource | None, typer.Option("--lc-source")] = None,
    lc_policy: Annotated[Path | None, typer.Option("--lc-policy")] = None,
    zenoh_config: ZenohConfigOpt = None,
    ros2: Ros2Opt = False,
    rgb_topic: RgbTopicOpt = None,
    depth_topic: DepthTopicOpt = None,
    camera_info_topic: InfoTopicOpt = None,
    ros_domain_id: DomainOpt = None,
    odom_topic: OdomTopicOpt = None,
    detections_topic: DetectionsTopicOpt = None,
    rerun: RerunOpt = False,
    rerun_web: RerunWebOpt = None,
    rrd: RrdOpt = None,
    live: Annotated[
        bool, typer.Option("--live", help="latency first for a live camera: track the newest frame (ingest.live)")
    ] = False,
) -> None:
    """Run the long-lived mapping service (until SIGINT / SIGTERM); with --ros2 it also takes ROS 2 topics."""
    from service.run import serve as serve_forever

    topics = (rgb_topic, depth_topic, camera_info_topic, ros_domain_id, odom_topic, detections_topic)
    extra = {"ros2": ros} if (ros := ros2_overrides(ros2, *topics)) else {}
    extra |= viewer_overrides(rerun, rerun_web, rrd)
    if live:
        extra["ingest"] = {"live": True}
    settings = _settings(config, robot, connect, listen, mode, state_dir, zenoh_config, extra)
    code = serve_forever(_with_lc(settings, lc_source, lc_policy))
    if code:  # some outputs could not be written on shutdown (logged one line each)
        sys.exit(code)


StrideOpt = Annotated[int | None, typer.Option("--stride", help="every N-th frame only (the dataset option stride=N)")]
DropOpt = Annotated[float | None, typer.Option("--drop", help="drop this fraction of the frames at random (drop=F)")]
DropSeedOpt = Annotated[int | None, typer.Option("--drop-seed", help="seed of --drop (drop_seed=S)")]


def _view_spec(dataset: str, stride: int | None, drop: float | None, drop_seed: int | None) -> str:
    """The dataset spec with ``--stride`` / ``--drop`` / ``--drop-seed`` as its options (``sources.VIEW_OPTIONS``)."""
    options = {"stride": stride, "drop": drop, "drop_seed": drop_seed}
    extra = "&".join(f"{k}={v}" for k, v in options.items() if v is not None)
    return dataset if not extra else f"{dataset}{'&' if '?' in dataset else '?'}{extra}"


@app.command()
def replay(
    dataset: Annotated[str, typer.Argument(help="directory or synthetic:NAME?seed=N&frames=N")],
    rate: Annotated[float | None, typer.Option("--rate", help="frames per second (default: timestamps)")] = None,
    max_rate: Annotated[bool, typer.Option("--max-rate", help="publish as fast as possible")] = False,
    max_frames: Annotated[int | None, typer.Option("--max-frames")] = None,
    robot: RobotOpt = None,
    connect: ConnectOpt = None,
    mode: ModeOpt = None,
    config: ConfigOpt = None,
    depth_scale: Annotated[float | None, typer.Option("--depth-scale")] = None,
    fx: Annotated[float | None, typer.Option("--fx")] = None,
    fy: Annotated[float | None, typer.Option("--fy")] = None,
    cx: Annotated[float | None, typer.Option("--cx")] = None,
    cy: Annotated[float | None, typer.Option("--cy")] = None,
    stride: StrideOpt = None,
    drop: DropOpt = None,
    drop_seed: DropSeedOpt = None,
    zenoh_config: ZenohConfigOpt = None,
    rgb_topic: RgbTopicOpt = None,
    depth_topic: DepthTopicOpt = None,
    camera_info_topic: InfoTopicOpt = None,
    ros_domain_id: DomainOpt = None,
    odom_topic: OdomTopicOpt = None,
    detections_topic: DetectionsTopicOpt = None,
) -> None:
    """Publish a dataset's frames to a running service (protocol v1); a rosbag2 recording with the topic flags
    is published as ROS 2 messages on rmw_zenoh keys (for `serve --ros2`)."""
    from service.replay import Replayer, frame_publisher
    from service.zenoh_session import open_session
    from sources import open_dataset

    if rate is not None and max_rate:
        raise UserError("--rate and --max-rate are exclusive")
    positive_finite("--rate", rate)
    settings = _settings(config, robot, connect, None, mode, zenoh_config=zenoh_config)
    bag_topics = ros_topics(rgb_topic, depth_topic, camera_info_topic, odom_topic, detections_topic)
    if bag_topics is not None and is_rosbag(dataset):
        from service.ros2_replay import replay_rosbag

        session = open_session(settings.zenoh, "client")
        try:
            domain = settings.ros2.domain_id if ros_domain_id is None else ros_domain_id
            result = replay_rosbag(session, Path(dataset), bag_topics, domain, rate, max_rate, max_frames)
        finally:
            session.close()
        console.print(f"published {result.frames} ROS 2 frames in {result.seconds:.1f} s")
        return
    data = open_dataset(
        _view_spec(dataset, stride, drop, drop_seed),
        _camera_overrides(depth_scale=depth_scale, fx=fx, fy=fy, cx=cx, cy=cy),
        settings.camera.model_dump(),
    )
    session = open_session(settings.zenoh, "client")
    try:
        pub = frame_publisher(session, f"{settings.key_prefix}/rgbd", settings.zenoh.query_timeout_s, required=True)
        result = Replayer(data, pub.put, rate_hz=rate, max_rate=max_rate, max_frames=max_frames).run()
        pub.undeclare()
    finally:
        session.close()
    console.print(f"published {result.frames} frames in {result.seconds:.1f} s ({result.rate_hz:.1f} frames/s)")


@app.command()
def save(
    robot: RobotOpt = None,
    connect: ConnectOpt = None,
    mode: ModeOpt = None,
    config: ConfigOpt = None,
    timeout: Annotated[float, typer.Option("--timeout", help="seconds to wait for the files")] = 120.0,
    as_json: Annotated[bool, typer.Option("--json", help="print the JSON reply")] = False,
    zenoh_config: ZenohConfigOpt = None,
) -> None:
    """Ask a running service to write its outputs (trajectory, objects, loops, report, map) into its state dir."""
    from service.client import query

    positive_finite("--timeout", timeout)
    reply = query(_settings(config, robot, connect, None, mode, zenoh_config=zenoh_config), "save", timeout)
    if as_json:
        print(json.dumps(reply, indent=1))
    else:
        files = ", ".join(map(str, reply.get("files", [])))
        console.print(  # plain text: the reply's strings are data, not rich markup
            Text(
                f"{reply.get('robot')}: {reply.get('keyframes')} keyframes of {reply.get('frames_processed')} frames "
                f"written to {reply.get('dir')} in {reply.get('seconds')} s: {files}"
            )
        )


@app.command()
def status(
    what: Annotated[QueryKind, typer.Argument()] = QueryKind.status,
    as_json: Annotated[bool, typer.Option("--json", help="print the JSON reply")] = False,
    robot: RobotOpt = None,
    connect: ConnectOpt = None,
    mode: ModeOpt = None,
    config: ConfigOpt = None,
    zenoh_config: ZenohConfigOpt = None,
) -> None:
    """Query a running service (status, objects, trajectory or loops)."""
    from service.client import query, render_reply

    settings = _settings(config, robot, connect, None, mode, zenoh_config=zenoh_config)
    reply = query(settings, what.value)
    if as_json:
        print(json.dumps(reply, indent=1))
    else:
        render_reply(console, what.value, reply)


@app.command()
def run(
    dataset: Annotated[str, typer.Argument(help="directory or synthetic:NAME?seed=N&frames=N")],
    out: Annotated[Path, typer.Option("--out", help="output directory")],
    config: ConfigOpt = None,
    max_frames: Annotated[int | None, typer.Option("--max-frames")] = None,
    lc_source: Annotated[LcSource | None, typer.Option("--lc-source")] = None,
    lc_policy: Annotated[Path | None, typer.Option("--lc-policy")] = None,
    depth_scale: Annotated[float | None, typer.Option("--depth-scale")] = None,
    fx: Annotated[float | None, typer.Option("--fx")] = None,
    fy: Annotated[float | None, typer.Option("--fy")] = None,
    cx: Annotated[float | None, typer.Option("--cx")] = None,
    cy: Annotated[float | None, typer.Option("--cy")] = None,
    stride: StrideOpt = None,
    drop: DropOpt = None,
    drop_seed: DropSeedOpt = None,
    rgb_topic: RgbTopicOpt = None,
    depth_topic: DepthTopicOpt = None,
    camera_info_topic: InfoTopicOpt = None,
    odom_topic: OdomTopicOpt = None,
    detections_topic: DetectionsTopicOpt = None,
    rerun: RerunOpt = False,
    rerun_web: RerunWebOpt = None,
    rrd: RrdOpt = None,
    no_rrd: NoRrdOpt = False,
) -> None:
    """Run the whole pipeline on one dataset (or a rosbag2 recording, with the topic flags) over an embedded zenoh
    session; write the outputs."""
    from service.outputs import EXIT_OUTPUTS_FAILED, OutputsError, check_output_dir
    from service.run import run_dataset
    from service.summary import print_summary
    from sources import Dataset, open_dataset

    check_output_dir(out, "--out")
    spec: str | Dataset = _view_spec(dataset, stride, drop, drop_seed)
    bag_topics = ros_topics(rgb_topic, depth_topic, camera_info_topic, odom_topic, detections_topic)
    if bag_topics is not None:
        spec = open_dataset(dataset, ros_topics=bag_topics)
    try:
        summary = run_dataset(
            spec,
            out,
            _with_lc(_settings(config, extra=viewer_overrides(rerun, rerun_web, rrd, no_rrd)), lc_source, lc_policy),
            max_frames,
            _camera_overrides(depth_scale=depth_scale, fx=fx, fy=fy, cx=cx, cy=cy),
        )
    except OutputsError as exc:  # the run is done; what was written is summarised, the failures were logged
        print_summary(console, exc.summary, out)
        print(f"objslam: error: {exc}", file=sys.stderr)
        sys.exit(EXIT_OUTPUTS_FAILED)
    print_summary(console, summary, out)


@app.command("eval")
def evaluate_cmd(
    run_dir: Annotated[Path, typer.Argument(help="a run output directory")],
    gt: Annotated[str, typer.Option("--gt", help="the dataset with ground truth")],
    objects_gt: Annotated[
        Path | None,
        typer.Option(
            "--objects-gt",
            help="object ground truth to score against (default: the dataset's own, or "
            "the repository's annotation of that dataset, evaluation/data/*/objects_gt.json)",
        ),
    ] = None,
) -> None:
    """A run directory against a dataset's ground truth: ATE / RPE and, with ground-truth objects, object
    metrics; writes its section of report.md, metrics.json and eval.png."""
    from service.evaluate import evaluate_run

    console.print(evaluate_run(run_dir, gt, objects_gt))


@app.command("config")
def config_cmd(
    dump: Annotated[bool, typer.Option("--dump", help="print the default configuration")] = False,
    config: ConfigOpt = None,
) -> None:
    """Print the default configuration (--dump) or the effective one."""
    import yaml

    if dump:
        print(dump_defaults(), end="")
    else:
        print(yaml.safe_dump(load_settings(config).model_dump(mode="json"), sort_keys=False), end="")


bench_commands.register(app)
lc_cli.register(app, console, UserError)


def single_threaded_blas() -> None:
    """numpy's BLAS on one thread for the whole process.

    The pipeline's products are small (N x 3 by 3 x 3); on a shared 2-core machine OpenBLAS's thread pool
    made them 10x slower (68k points: 61 ms with 2 threads under load, 4.7 ms with one), and the service
    has its own threads. The detector (onnxruntime) and the trainer (torch) size their own thread pools.
    """
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")


def main() -> None:
    """Console entry point: domain errors become one line on stderr and exit code 1 (``serve`` and ``run``: 3 when
    some output files could not be written, ``service.outputs.EXIT_OUTPUTS_FAILED``)."""
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    ours = ("service", "slam", "loops", "perception", "graph", "rl", "sources", "evaluation", "bench")
    for package in ours:  # progress messages of ours; other libraries' warnings only
        logging.getLogger(package).setLevel(logging.INFO)
    single_threaded_blas()
    try:
        app(standalone_mode=False)
    except (UserError, ConfigError, DatasetError, ConnectionError, TimeoutError, RuntimeError, OSError) as exc:
        print(f"objslam: error: {' '.join(str(exc).split())}", file=sys.stderr)
        sys.exit(1)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except (typer.Abort, KeyboardInterrupt):
        sys.exit(130)
    except Exception as exc:  # usage errors of typer's bundled click carry show() and exit_code
        if hasattr(exc, "show") and hasattr(exc, "exit_code"):
            exc.show()
            sys.exit(exc.exit_code)
        raise
