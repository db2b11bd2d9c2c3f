"""Two robots through one zenoh router: `serve --robot a` and `--robot b`, each fed by its own replay client."""

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

pytestmark = pytest.mark.integration
ROBOTS = {  # robot -> (dataset, frames): different seeds and lengths, small images so replay is quick
    "a": ("synthetic:room?seed=1&frames=40&width=160&height=120", 40),
    "b": ("synthetic:room?seed=2&frames=25&width=160&height=120", 25),
}


def _objslam(*args: str, env: dict[str, str] | None = None) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "service", *args],
        env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def _get(session: zenoh.Session, key: str, timeout: float = 5.0) -> dict | None:
    for reply in session.get(key, timeout=timeout):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    return None


def _wait(predicate, what: str, timeout: float = 60.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = predicate()
        if value:
            return value
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for {what}")


def _finished_status(session: zenoh.Session, robot: str, frames: int, timeout: float = 240.0) -> dict:
    """The robot's status once every frame it was sent is processed, rejected or dropped."""
    end, status = time.monotonic() + timeout, None
    while time.monotonic() < end:
        status = _get(session, f"objslam/{robot}/status", timeout=2.0) or status
        if status and status["frames_processed"] + status["frames_rejected_total"] + status["frames_dropped"] >= frames:
            return status
        time.sleep(0.2)
    raise AssertionError(f"robot {robot} did not finish its {frames} frames; last status: {status}")


def _stop(proc: subprocess.Popen) -> str:
    proc.send_signal(signal.SIGTERM)
    try:
        return proc.communicate(timeout=30)[0]
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.communicate()[0]


def test_two_robots_on_one_router_keep_separate_maps_and_status(router):
    session, endpoint = router
    client = ["--mode", "client", "--connect", endpoint]
    # a queue large enough for the whole replay: this test is about isolation, not about keeping up; odometry
    # factors only (no loop closures, objects not in the graph), so each trajectory must be its own odometry
    serves = {
        r: _objslam(
            "serve",
            "--robot",
            r,
            *client,
            "--lc-source",
            "off",
            env={"OBJSLAM_INGEST__QUEUE_SIZE": "512", "OBJSLAM_OBJECTS__LANDMARKS": "false"},
        )
        for r in ROBOTS
    }
    try:
        for r in ROBOTS:
            _wait(lambda r=r: _get(session, f"objslam/{r}/status", timeout=1.0), f"robot {r} to serve")
        replays = {
            r: _objslam("replay", spec, "--rate", "20", "--robot", r, *client) for r, (spec, _) in ROBOTS.items()
        }  # both publish at the same time
        for proc in replays.values():
            out, _ = proc.communicate(timeout=120)
            assert proc.returncode == 0, out

        statuses = {}
        for r, (_, frames) in ROBOTS.items():
            statuses[r] = _finished_status(session, r, frames)
        trajectories = {}
        for r, (spec, frames) in ROBOTS.items():
            status = statuses[r]
            assert status["robot"] == r
            assert status["frames_received"] == frames  # only its own frames reached it
            assert status["frames_processed"] == frames and status["frames_dropped"] == 0, status
            rows = np.array(_get(session, f"objslam/{r}/trajectory")["poses"])
            assert rows.shape == (frames, 8)
            # with odometry factors only a robot's trajectory is its own chained odometry
            dataset = open_dataset(spec)
            odometry = np.stack([dataset.frame(i).odometry for i in range(frames)])
            np.testing.assert_allclose(np.stack([pose_from_tum(row[1:]) for row in rows]), odometry, atol=1e-6)
            trajectories[r] = rows
        n = min(len(t) for t in trajectories.values())
        assert np.abs(trajectories["a"][:n, 1:4] - trajectories["b"][:n, 1:4]).max() > 0.05  # different paths

        cli = subprocess.run(
            [sys.executable, "-m", "service", "status", "--json", "--robot", "b", *client],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert cli.returncode == 0, cli.stderr
        assert json.loads(cli.stdout)["frames_received"] == ROBOTS["b"][1]
    finally:
        logs = {r: _stop(proc) for r, proc in serves.items()}
    for r, proc in serves.items():
        assert proc.returncode == 0, logs[r]
