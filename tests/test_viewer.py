"""The Rerun viewer: the ``.rrd`` every ``run`` records, what it holds, and a viewer that never slows the map."""

from __future__ import annotations

import subprocess
import threading
from collections import defaultdict
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from rerun.chunk import RrdReader
from typer.testing import CliRunner

import service.viewer_feed
from perception.frame import Detection
from service.cli import app
from service.config import load_settings
from service.protocol import encode_frame
from service.run import run_dataset
from service.viewer import ViewerSink, class_colour, decimate, ellipsoid
from service.viewer_cli import viewer_overrides
from service.viewer_connect import native_viewer, open_outlets, rerun_executable
from service.viewer_feed import CoreTracks, Keyframe, ViewerFeed
from slam.build import build_core
from sources import open_dataset
from tests.conftest import REDKITCHEN, free_port, requires_redkitchen

pytestmark = pytest.mark.integration
SCENE = "synthetic:room?seed=0&frames=40&width=160&height=120"
SCENE_ENTITIES = {
    "/world/camera",
    "/world/camera/rgb",
    "/world/camera/depth",
    "/world/camera/detections",
    "/world/trajectory",
    "/world/odometry",
    "/world/ground_truth",
    "/world/objects",
    "/world/landmarks",
    "/world/loops/accepted",
    "/world/loops/rejected",
    "/world/map_points",
}


def _settings(**viewer):
    return load_settings(None, {"detector": {"enabled": False}, "viewer": viewer})


def read_rrd(path: Path) -> tuple[dict[str, set[str]], dict[str, list]]:
    """Entity -> component and timeline columns; and ``entity:column`` -> the values logged, oldest first."""
    columns: dict[str, set[str]] = defaultdict(set)
    values: dict[str, list] = defaultdict(list)
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        columns[chunk.entity_path] |= set(batch.schema.names)
        for name in batch.schema.names:
            values[f"{chunk.entity_path}:{name}"] += batch.column(name).to_pylist()
    return columns, values


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("run")
    summary = run_dataset(SCENE, out, _settings(), progress=False)
    return out, summary


def test_run_writes_a_map_rrd_that_rerun_verifies(recorded):
    out, summary = recorded
    assert summary["frames_processed"] == 40
    result = subprocess.run([rerun_executable(), "rrd", "verify", str(out / "map.rrd")], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr + result.stdout


def test_the_recording_holds_camera_trajectories_objects_loops_and_timelines(recorded):
    out, _ = recorded
    columns, values = read_rrd(out / "map.rrd")
    assert set(columns) >= SCENE_ENTITIES, SCENE_ENTITIES - set(columns)
    assert {"Transform3D:translation", "Pinhole:image_from_camera", "frame", "sensor_time"} <= columns["/world/camera"]
    assert "EncodedImage:blob" in columns["/world/camera/rgb"]
    assert "EncodedDepthImage:blob" in columns["/world/camera/depth"]
    assert values["/world/camera/detections:Boxes2D:labels"][-1], "the keyframe's detection boxes"
    frames = [f for f in values["/world/camera:frame"] if f is not None]
    assert frames == sorted(frames) and frames[-1] == 40  # the last update is the map after the 40th frame
    labels = values["/world/objects:Ellipsoids3D:labels"][-1]
    objects = __import__("json").loads((out / "objects.json").read_text())
    assert len(labels) == len(objects) > 0
    assert {f"{o['label']} #{o['id']} ({o['n_observations']} obs)" for o in objects} == set(labels)
    colours = values["/world/objects:Ellipsoids3D:colors"][-1]
    assert len(set(colours)) > 1  # coloured by class
    strip = values["/world/trajectory:LineStrips3D:strips"][-1][0]
    tum = np.loadtxt(out / "trajectory.tum")
    assert np.allclose(np.array(strip)[-1], tum[-1, 1:4], atol=1e-4)  # the final, optimised trajectory
    assert len(values["/world/ground_truth:LineStrips3D:strips"][-1][0]) == 40


def test_a_stalled_sink_leaves_the_pipeline_at_full_speed(tmp_path, monkeypatch):
    """A viewer that never returns from its first log call: every frame is processed, as fast as without a
    viewer (generous bound), and the run ends; the viewer got one update, the map all 60 frames."""
    spec = SCENE.replace("frames=40", "frames=60")
    plain = run_dataset(spec, tmp_path / "plain", _settings(enabled=False), progress=False)
    assert not (tmp_path / "plain" / "map.rrd").exists()

    release, calls = threading.Event(), []

    def stalled_log(self, update):
        calls.append(update.frame)
        release.wait(60.0)

    monkeypatch.setattr(ViewerSink, "log", stalled_log)
    monkeypatch.setattr(service.viewer_feed, "CLOSE_TIMEOUT_S", 0.2)
    try:
        stalled = run_dataset(spec, tmp_path / "stalled", _settings(max_rate_hz=50.0), progress=False)
    finally:
        release.set()
    assert plain["frames_processed"] == stalled["frames_processed"] == 60
    assert stalled["frames_dropped"] == plain["frames_dropped"] == 0
    assert len(calls) == 1  # the feed stalled in its first update and sent nothing more
    assert stalled["throughput_fps"] >= 0.5 * plain["throughput_fps"]
    assert (tmp_path / "stalled" / "map.rrd").is_file()  # closed all the same


def test_run_accepts_the_viewer_flags_and_goes_on_without_a_native_viewer(tmp_path, monkeypatch):
    """--rerun with no viewer listening and no display: a warning, the run and its --rrd recording complete."""
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setenv("OBJSLAM_VIEWER__CONNECT", f"rerun+http://127.0.0.1:{free_port()}/proxy")
    rrd = tmp_path / "chosen.rrd"
    args = ["run", SCENE.replace("frames=40", "frames=8"), "--out", str(tmp_path / "out"), "--rerun", "--rrd", str(rrd)]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert rrd.is_file() and not (tmp_path / "out" / "map.rrd").exists()
    result = CliRunner().invoke(app, ["serve", "--help"])
    assert all(flag in result.output for flag in ("--rerun", "--rerun-web", "--rrd"))


def test_no_native_viewer_and_no_display_is_no_sink():
    url = f"rerun+http://127.0.0.1:{free_port()}/proxy"
    assert native_viewer(url) is None or pytest.skip("a display is available: a viewer would be started")
    settings = _settings(native=True, connect=url).viewer
    assert open_outlets(settings, None, "r1") is None


def test_the_flags_set_the_viewer_settings():
    s = load_settings(None, viewer_overrides(True, 9090, Path("m.rrd"), no_rrd=True))
    assert (s.viewer.native, s.viewer.web_port, s.viewer.rrd, s.viewer.enabled) == (True, 9090, Path("m.rrd"), False)
    assert load_settings(None, viewer_overrides(False, None, None)).viewer == load_settings().viewer


def test_an_ellipsoid_reproduces_its_covariance():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(3, 3))
    cov = a @ a.T + 0.01 * np.eye(3)
    half, quat = ellipsoid(cov)
    from scipy.spatial.transform import Rotation

    r = Rotation.from_quat(quat).as_matrix()
    assert np.allclose(r @ np.diag((half / 1.5) ** 2) @ r.T, cov)


def test_decimation_keeps_the_ends_and_colours_are_fixed_per_class():
    pts = np.arange(30000).reshape(-1, 3)
    d = decimate(pts, 2000)
    assert len(d) == 2000 and (d[0] == pts[0]).all() and (d[-1] == pts[-1]).all()
    assert class_colour("chair") == class_colour("chair") and len({class_colour(c) for c in "abcdefgh"}) > 3


def test_the_feed_copies_the_core_s_trajectories_a_few_new_frames_at_a_time():
    """``CoreTracks`` copies only the new records (and the keyframe poses when the graph moved), yet composes
    the same trajectories as the core, with the keyframes among the new frames."""
    settings = _settings()
    core, data, tracks = build_core(settings), open_dataset(SCENE), CoreTracks()
    keyframes = []
    for i in range(len(data)):
        core.step(data.frame(i))
        if i % 7 == 6 or i == len(data) - 1:
            tracks.take(core)
            keyframes += tracks.new_keyframes()
            optimised, odometry = tracks.trajectories()
            expected = core.trajectory(tied_only=True)
            assert np.array_equal(optimised.timestamps, expected.timestamps)
            assert np.allclose(optimised.poses, expected.poses)
            assert np.allclose(odometry.poses, core.odometry_trajectory().poses)
    assert [(k.index, k.timestamp) for k in keyframes] == [
        (r.keyframe, r.timestamp) for r in core.records if r.is_keyframe
    ]
    assert tracks.take(core) is False  # nothing moved: the keyframe poses are not read again


def test_a_keyframe_s_image_is_its_own_frame_with_the_core_s_boxes_when_ready():
    """The tap holds newer frames than the keyframe: the keyframe's own message is found by its timestamp; its
    boxes are the frame's until the core's detections of it come, then those, at the image's time."""
    data = open_dataset(SCENE)
    feed = ViewerFeed(SimpleNamespace(limits=_settings().ingest), None, _settings().viewer)  # type: ignore[arg-type]
    for i in range(10):
        feed._on_frame(SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda i=i: encode_frame(data.frame(i)))))
    kf_time = data.frame(3).timestamp
    feed._keyframes = [Keyframe(1, kf_time)]
    message, boxes = feed._keyframe_message({1: None}, frame=9, when=data.frame(9).timestamp)
    assert message is not None and message.timestamp == kf_time and feed.images == 1
    assert boxes == (message.detections or [])
    assert feed._late_boxes({1: None}) is None  # the core's detections are not ready yet
    core_boxes = [Detection("chair", 0.9, (1.0, 2.0, 30.0, 40.0))]
    assert feed._late_boxes({1: core_boxes}) == (9, data.frame(9).timestamp, core_boxes)
    assert feed._late_boxes({1: core_boxes}) is None  # logged once
    assert feed._keyframe_message({1: core_boxes}, 10, 0.0) == (None, None)  # shown already


@requires_redkitchen
def test_keyframe_images_of_an_unregistered_camera_are_logged_one_after_another(tmp_path):
    """7-Scenes' depth camera is not registered to its colour camera (a 4 x 4 depth-to-colour transform): each
    keyframe's camera is compared with the last one's, which raised on the array and lost every image after the
    first on the real sequence."""
    import rerun as rr

    data = open_dataset(str(REDKITCHEN))
    assert not data.camera.registered
    feed = ViewerFeed(SimpleNamespace(limits=_settings().ingest), None, _settings().viewer)  # type: ignore[arg-type]
    rec = rr.RecordingStream("objslam-test")
    rec.save(tmp_path / "kitchen.rrd")
    sink = ViewerSink(rec)
    for i in (0, 10):
        feed._on_frame(SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda i=i: encode_frame(data.frame(i)))))
        feed._keyframes = [Keyframe(i, data.frame(i).timestamp)]
        message, _ = feed._keyframe_message({i: None}, frame=i, when=data.frame(i).timestamp)
        assert message is not None and message.camera == data.camera
        sink._log_images(message)
    rec.flush()
    _, values = read_rrd(tmp_path / "kitchen.rrd")
    blobs = [v for k, v in values.items() if k.startswith("/world/camera/rgb:") and "blob" in k.lower()]
    assert blobs and len(blobs[0]) == 2  # both keyframes' images
    assert sink.camera == data.camera
