"""The RL policy in the live service (issue 6): a synthetic scene replayed over real zenoh, the policy trained
for that scene's map (first pass) proposes loop closures, the geometric verifier accepts true ones only."""

from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest

from bench.rig import free_port, query_status, router, start_serve, stop_serve, wait_for_status
from graph.geometry import motion_magnitude, pose_from_tum, relative
from sources import open_dataset
from tests.conftest import ROOM_POLICY, requires_room_policy

pytestmark = pytest.mark.integration
POLICY = ROOM_POLICY
SPEC = "synthetic:room?seed=3&frames=300"


@requires_room_policy
def test_policy_proposals_become_verified_loop_closures_and_none_is_false():
    port = free_port()
    hub = router(port)
    endpoint = f"tcp/127.0.0.1:{port}"
    serve, log = start_serve(
        endpoint,
        "rl",
        env={
            "OBJSLAM_LOOPS__SOURCE": "policy",
            "OBJSLAM_LOOPS__POLICY": str(POLICY),
            "OBJSLAM_INGEST__QUEUE_SIZE": "512",
        },
    )
    try:
        wait_for_status(hub, "objslam/rl/status", serve, log)
        replay = subprocess.run(
            [
                sys.executable,
                "-m",
                "service",
                "replay",
                SPEC,
                "--rate",
                "30",
                "--robot",
                "rl",
                "--mode",
                "client",
                "--connect",
                endpoint,
            ],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert replay.returncode == 0, replay.stderr[-2000:]
        status: dict = {}
        for _ in range(1200):
            status = query_status(hub, "objslam/rl/status") or status
            if status.get("frames_processed", 0) >= 300:
                break
            time.sleep(0.25)
        assert status["frames_processed"] == 300, status
        loops = query_status(hub, "objslam/rl/loops", timeout=10.0)["loops"]
    finally:
        stop_serve(serve)
        hub.close()
    assert loops and {r["source"] for r in loops} == {"policy"}  # the only candidate source here
    accepted = [r for r in loops if r["accepted"]]
    assert len(accepted) >= 1, [r.get("reason") for r in loops]
    gt = open_dataset(SPEC).ground_truth.poses
    for r in accepted:  # none false: the verified relative pose agrees with the ground truth
        truth = relative(gt[r["match_frame"]], gt[r["query_frame"]])
        dt, dr = motion_magnitude(relative(truth, pose_from_tum(np.array(r["relative_pose"]))))
        assert dt < 0.05 and np.degrees(dr) < 3.0, r
        assert 0.0 < r["policy_probability"] <= 1.0
