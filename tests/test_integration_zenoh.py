"""End to end over real zenoh: a router on 127.0.0.1, `objslam serve` and `objslam replay` as subprocesses."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import zenoh

from graph.geometry import pose_from_tum
from sources import open_dataset
from tests.conftest import free_port

pytestmark = pytest.mark.integration
FRAMES = 100
SPEC = f"synthetic:room?seed=3&frames={FRAMES}"


def _objslam(*args: str, env: dict[str, str] | None = None, **kw) -> subprocess.Popen:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
    return subprocess.Popen([sys.executable, "-m", "service", *args], env=env, **kw)


def _get(session: zenoh.Session, key: str, timeout: float = 5.0) -> dict | None:
    for reply in session.get(key, timeout=timeout):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    return None


def _wait_for_service(session: zenoh.Session, key: str, deadline_s: float = 60.0) -> dict:
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        reply = _get(session, key, timeout=1.0)
        if reply is not None:
            return reply
        time.sleep(0.2)
    raise AssertionError(f"service never answered on {key}")


def test_replayed_frames_are_all_processed_and_trajectory_equals_chained_odometry(router, tmp_path):
    session, endpoint = router
    common = ["--mode", "client", "--connect", endpoint, "--robot", "itest"]
    serve_only = ["--lc-source", "off"]
    # odometry factors only (no loop closures, objects not in the graph): the estimate must equal the chain
    serve = _objslam(
        "serve",
        *common,
        *serve_only,
        "--state-dir",
        str(tmp_path / "state"),
        env={"OBJSLAM_OBJECTS__LANDMARKS": "false"},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        _wait_for_service(session, "objslam/itest/status")
        replay = _objslam(
            "replay", SPEC, "--rate", "15", *common, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        )
        out, _ = replay.communicate(timeout=240)
        assert replay.returncode == 0, out
        status = {}
        for _ in range(600):  # let the worker drain its queue (up to 60 s on a loaded machine)
            status = _get(session, "objslam/itest/status")
            if status["frames_processed"] + status["frames_rejected_total"] >= FRAMES:
                break
            time.sleep(0.1)
        assert status["frames_received"] == FRAMES
        assert status["frames_processed"] == FRAMES, status
        assert status["frames_rejected"] == {} and status["frames_dropped"] == 0
        assert 1 < status["keyframes"] < FRAMES and status["protocol_version"] == 1
        tracking = status["tracking"]
        assert tracking["state"] == "tracking" and tracking["methods"] == {"odometry": FRAMES}
        assert tracking["segments"] == 1 and tracking["segments_unjoined"] == 0 and tracking["untied_frames"] == []

        cli = subprocess.run(
            [sys.executable, "-m", "service", "status", "--json", *common], capture_output=True, text=True, timeout=60
        )
        assert cli.returncode == 0, cli.stderr
        assert json.loads(cli.stdout)["frames_processed"] == FRAMES

        traj = _get(session, "objslam/itest/trajectory")
        rows = np.array(traj["poses"])
        assert rows.shape == (FRAMES, 8)
        dataset = open_dataset(SPEC)
        odometry = np.stack([dataset.frame(i).odometry for i in range(FRAMES)])
        np.testing.assert_allclose(rows[:, 0], dataset.timestamps[:FRAMES], atol=1e-9)
        estimate = np.stack([pose_from_tum(r[1:]) for r in rows])
        np.testing.assert_allclose(estimate, odometry, atol=1e-6)
    finally:
        serve.send_signal(signal.SIGTERM)
        try:
            log, _ = serve.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            serve.kill()
            log, _ = serve.communicate()
    assert serve.returncode == 0, log
    assert (tmp_path / "state" / "trajectory.tum").is_file()


def test_status_without_a_service_fails_with_one_clear_line(tmp_path):
    port = free_port()
    cli = subprocess.run(
        [sys.executable, "-m", "service", "status", "--connect", f"tcp/127.0.0.1:{port}", "--mode", "client"],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "OBJSLAM_ZENOH__QUERY_TIMEOUT_S": "1"},
    )
    assert cli.returncode != 0
    assert "objslam: error:" in cli.stderr and len(cli.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("args", [["--rate", "0"], ["--rate", "5", "--max-rate"]])
def test_replay_with_an_invalid_rate_fails_with_one_clear_line(args):
    cli = subprocess.run(
        [sys.executable, "-m", "service", "replay", "synthetic:room?frames=3", *args],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert cli.returncode == 1 and "Traceback" not in cli.stderr
    assert cli.stderr.strip().startswith("objslam: error: --rate") and len(cli.stderr.strip().splitlines()) == 1
