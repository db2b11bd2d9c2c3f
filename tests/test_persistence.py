"""Persistence: exact state round trips, atomic checksummed snapshots, and resuming ``serve --state-dir``.

The in-process reference feeds the same protocol-v1 payloads to a Pipeline; a resumed service must match
it exactly (the graph is rebuilt by replaying iSAM2's update log, not re-optimised).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import time
from itertools import pairwise

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from graph.geometry import pose_from_tum
from graph.pose_graph import PoseGraph
from service.config import ConfigError, load_settings
from service.map_persistence import Persistence
from service.map_store import MapStore
from service.node import ServiceNode
from service.persistence import HEADER, SnapshotError, SnapshotStore, decode, encode, seal, unseal
from service.protocol import decode_frame, encode_frame
from service.replay import frame_publisher
from service.zenoh_session import open_session
from slam.build import build_core
from slam.core import MAPPING_LAG
from slam.snapshot import core_state, restore_core
from sources import open_dataset
from tests.test_integration_zenoh import _get, _wait_for_service

FRAMES = 160
SPEC = f"synthetic:room?seed=0&frames={FRAMES}&fps=10&width=320&height=240"
EVERY = 5  # persistence.every_keyframes in these tests
CUT = 150  # the in-process round trip: after the first loop closures, before the last ones


@pytest.fixture(scope="module")
def payloads() -> list[bytes]:
    ds = open_dataset(SPEC)
    return [encode_frame(ds.frame(i)) for i in range(FRAMES)]


@pytest.fixture(scope="module")
def reference(payloads):
    """An uninterrupted in-process run: trajectory after each number of frames, final loops and objects,
    and at frame CUT its state as snapshot bytes, loop records and objects."""
    p = build_core(load_settings())
    after = [np.zeros((0, 4, 4))]
    keyframes = [0]
    at_cut = {}
    for i, payload in enumerate(payloads):
        p.step(decode_frame(payload))
        after.append(p.trajectory().poses)
        keyframes.append(p.graph.num_keyframes)
        if i + 1 == CUT:
            at_cut = {
                "snapshot": seal(encode(core_state(p))),
                "loops": [r.to_json() for r in p.loop_records()],
                "objects": p.object_list(),
                "accepted": dict(p.loops.accepted),
            }
    return {
        "after": after,
        "keyframes": keyframes,
        "loops": [r.to_json() for r in p.loop_records()],
        "objects": p.object_list(),
        "cut": at_cut,
    }


def _round_trip(state: dict) -> dict:
    return decode(unseal(seal(encode(state))))


# ------------------------------------------------------------ (a) exact round trips


def _loop_square(drift_deg: float = 0.6) -> tuple[list[np.ndarray], np.ndarray]:
    true = [np.eye(4)]
    for i in range(1, 41):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("z", 2 * np.pi * i / 40).as_matrix()
        T[:3, 3] = [np.cos(2 * np.pi * i / 40) - 1, np.sin(2 * np.pi * i / 40), 0.0]
        true.append(T)
    drift = np.eye(4)
    drift[:3, :3] = Rotation.from_euler("z", drift_deg, degrees=True).as_matrix()
    return true, drift


def test_pose_graph_replayed_from_state_is_identical_and_retracted_factors_stay_removed():
    true, drift = _loop_square()
    g = PoseGraph()
    g.add_first(true[0])
    for a, b in pairwise(true):
        g.add_keyframe(np.linalg.inv(a) @ b @ drift)
    g.add_between(10, 12, np.linalg.inv(true[10]) @ true[12], 0.02, 1.0)
    kept = g.add_loop(0, 40, np.linalg.inv(true[0]) @ true[40], 0.01, 0.5)
    wrong = g.add_loop(0, 20, np.linalg.inv(true[0]) @ true[20] @ drift, 0.01, 0.5)
    g.remove_factors([wrong])

    h = PoseGraph.from_state(_round_trip(g.state()))
    assert np.array_equal(h.poses(), g.poses())
    assert (h.num_keyframes, h.num_factors, h.updates) == (g.num_keyframes, g.num_factors, g.updates)
    assert not h.isam.getFactorsUnsafe().exists(wrong) and h.isam.getFactorsUnsafe().exists(kept)
    indices = []
    for graph in (g, h):  # both continue identically, factor indices included
        graph.add_keyframe(np.eye(4))
        indices.append(graph.add_loop(5, 41, np.linalg.inv(true[5]) @ true[40], 0.01, 0.5))
    assert indices[0] == indices[1] == len(g.factors) - 1 and np.array_equal(h.poses(), g.poses())
    assert np.array_equal(h.marginal_covariance(20), g.marginal_covariance(20))


def test_pipeline_restored_mid_run_continues_exactly_like_an_uninterrupted_run(payloads, reference):
    cut = reference["cut"]
    restored = restore_core(load_settings(), decode(unseal(cut["snapshot"])))
    assert restored.loops.n_accepted > 0 and restored.loops.accepted.keys() == cut["accepted"].keys()
    assert np.array_equal(restored.trajectory().poses, reference["after"][CUT])
    assert [r.to_json() for r in restored.loop_records()] == cut["loops"] and restored.object_list() == cut["objects"]
    for payload in payloads[CUT:]:
        restored.step(decode_frame(payload))
    assert np.array_equal(restored.trajectory().poses, reference["after"][FRAMES])
    assert [r.to_json() for r in restored.loop_records()] == reference["loops"] and len(restored.loop_records()) > 1
    assert restored.object_list() == reference["objects"] and len(reference["objects"]) > 3


def test_visual_odometry_state_round_trip_continues_exactly():
    ds = open_dataset("synthetic:room?seed=2&frames=300&width=320&height=240")
    frames = [ds.frame(i) for i in range(40)]
    for f in frames:
        f.odometry = None  # the RGB-D front end
    settings = load_settings(None, {"loops": {"source": "off"}})
    a = build_core(settings)
    for f in frames[:25]:
        a.step(f)
    b = restore_core(settings, _round_trip(core_state(a)))
    for f in frames[25:]:
        a.step(f)
        b.step(f)
    assert a.graph.num_keyframes > 5 and np.array_equal(a.trajectory().poses, b.trajectory().poses)
    assert np.array_equal(a.odometry_trajectory().poses, b.odometry_trajectory().poses)


# ------------------------------------------------------------ (d) the snapshot files


def test_store_keeps_the_newest_snapshots_and_removes_unfinished_writes(tmp_path):
    (tmp_path / ".snapshot-crash.tmp").write_bytes(b"half a snapshot")
    store = SnapshotStore(tmp_path, keep=3)
    assert not list(tmp_path.glob(".snapshot-*"))
    for i in range(5):
        store.write(encode({"i": i}))
    assert [p.name for p in store.snapshots()] == [f"snapshot-0000000{i}.bin" for i in (3, 4, 5)]
    assert [s["i"] for _, s in store.candidates([])] == [4, 3, 2]
    store.write(encode({"array": np.arange(5.0)}))
    array = next(store.candidates([]))[1]["array"]
    assert np.array_equal(array, np.arange(5.0)) and array.flags.writeable


@pytest.mark.parametrize(
    "damage, reason",
    [
        (lambda b: b[: len(b) // 2], "truncated"),
        (lambda b: b[:20], "truncated"),
        (lambda b: b[:-1] + bytes([b[-1] ^ 1]), "checksum mismatch"),
        (lambda b: b"NOTSNAP!" + b[8:], "bad magic"),
    ],
)
def test_a_damaged_newest_snapshot_is_skipped_with_its_reason(tmp_path, damage, reason):
    store = SnapshotStore(tmp_path, keep=3)
    store.write(encode({"i": 1}))
    newest = store.write(encode({"i": 2})).path
    newest.write_bytes(damage(newest.read_bytes()))
    skipped: list = []
    assert [s["i"] for _, s in store.candidates(skipped)] == [1]
    assert skipped[0][0] == newest.name and reason in skipped[0][1]


def test_a_snapshot_referring_to_anything_but_plain_data_is_refused_without_running_it(tmp_path):
    class Evil:
        def __reduce__(self):
            return (os.system, (f"touch {tmp_path / 'pwned'}",))

    with pytest.raises(SnapshotError, match="not plain data"):
        decode(unseal(seal(encode({"evil": Evil()}))))
    assert not (tmp_path / "pwned").exists()
    assert HEADER.size == 48


def test_resume_refuses_another_robots_state_dir(tmp_path):
    assert Persistence(tmp_path, "alpha").save({}, {}, 1, 1)
    with pytest.raises(ConfigError, match="alpha"):
        Persistence(tmp_path, "beta")


def _feed(node: ServiceNode, session, payloads: list[bytes]) -> None:
    pub = frame_publisher(session, f"{node.prefix}/rgbd")
    target = node.stats.received + len(payloads)
    for payload in payloads:
        pub.put(payload)
    assert node.wait_done(target, timeout=120.0)
    assert node.queue.dropped == 0
    pub.undeclare()


def test_corrupt_newest_checkpoint_falls_back_to_the_previous_one_and_reports_it(tmp_path, payloads, reference, caplog):
    settings = load_settings(
        None, {"state_dir": tmp_path, "persistence": {"every_keyframes": EVERY}, "ingest": {"queue_size": 1000}}
    )  # zenoh delivers in bursts: drop nothing
    session = open_session(settings.zenoh, "server", embedded=True)
    try:
        node = ServiceNode(settings, session)
        node.start()
        _feed(node, session, payloads[:60])
        node.stop()  # the final checkpoint (60 frames) after the periodic ones
        store = MapStore(tmp_path / "map.db", settings.robot)
        ids = [c[0] for c in store.checkpoints()]
        assert len(ids) == 3 and node.persistence.written >= 3
        store.db.execute("UPDATE checkpoints SET small = substr(small, 1, length(small) - 1000) WHERE id = ?", ids[:1])
        store.close()  # the newest one's state lost its last 1000 bytes, as a torn page would

        with caplog.at_level(logging.ERROR, logger="service.map_store"):
            resumed = ServiceNode(settings, session)
        assert f"checkpoint {ids[0]} is unusable" in caplog.text and "checksum mismatch" in caplog.text
        status = resumed.status()["persistence"]
        assert status["resumed_from"]["file"] == f"map.db#checkpoint-{ids[1]}"
        assert status["skipped_snapshots"][0]["file"] == f"checkpoint-{ids[0]}"
        m = status["resumed_from"]["frames_processed"]
        assert m < 60 and status["resumed_from"]["keyframes"] >= EVERY  # a periodic one (perhaps deferred while
        # the keyframe mapping ran: at most MAPPING_LAG keyframes)
        assert resumed.status()["frames_processed"] == m
        assert np.array_equal(resumed.trajectories()[0].poses, reference["after"][m])

        resumed.start()  # the client re-sends everything: old frames are rejected, the rest continue the map
        _feed(resumed, session, payloads[:80])
        status = resumed.status()
        assert status["frames_processed"] == 80 and sum(status["frames_rejected"].values()) == m, status
        assert np.array_equal(resumed.trajectories()[0].poses, reference["after"][80])
        resumed.stop()
    finally:
        session.close()


# ------------------------------------------------------------ (b, c) serve in a subprocess


def _objslam(*args: str, **kw) -> subprocess.Popen:
    env = {
        **os.environ,
        "PYTHONUNBUFFERED": "1",
        "OBJSLAM_PERSISTENCE__EVERY_KEYFRAMES": str(EVERY),
        "OBJSLAM_INGEST__QUEUE_SIZE": "1000",
    }
    return subprocess.Popen([sys.executable, "-m", "service", *args], env=env, **kw)


def _serve(endpoint: str, state_dir, log_path) -> subprocess.Popen:
    with open(log_path, "a") as log:  # the child keeps its own handle
        return _objslam(
            "serve",
            "--mode",
            "client",
            "--connect",
            endpoint,
            "--robot",
            "ptest",
            "--state-dir",
            str(state_dir),
            stdout=log,
            stderr=subprocess.STDOUT,
        )


def _replay(endpoint: str, max_frames: int, rate: float | None = None) -> subprocess.Popen:
    pace = ["--rate", str(rate)] if rate else ["--max-rate"]
    return _objslam(
        "replay",
        SPEC,
        *pace,
        "--max-frames",
        str(max_frames),
        "--mode",
        "client",
        "--connect",
        endpoint,
        "--robot",
        "ptest",
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def _wait_handled(session, frames: int, timeout: float = 90.0, replay: subprocess.Popen | None = None) -> dict:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        status = _get(session, "objslam/ptest/status")
        if status and status["frames_processed"] + status["frames_rejected_total"] >= frames:
            return status
        time.sleep(0.1)
    said = replay.stdout.read() if replay is not None else ""  # e.g. its warning that no subscriber matched
    raise AssertionError(f"the service did not handle {frames} frames in {timeout} s: {status}; replay: {said}")


def _trajectory(session) -> np.ndarray:
    return np.array(_get(session, "objslam/ptest/trajectory")["poses"]).reshape(-1, 8)


def _same_poses(rows: np.ndarray, poses: np.ndarray) -> None:
    assert len(rows) == len(poses)
    np.testing.assert_allclose(
        np.stack([pose_from_tum(r[1:]) for r in rows]).reshape(-1, 4, 4), poses, atol=1e-9, rtol=0
    )


def _stop(proc: subprocess.Popen, sig=signal.SIGTERM, timeout: float = 60.0) -> int:
    proc.send_signal(sig)
    try:
        return proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        raise


@pytest.mark.integration
def test_frames_still_queued_at_stop_are_counted_as_dropped_in_the_final_snapshot(tmp_path, payloads):
    settings = load_settings(None, {"state_dir": tmp_path, "detector": {"enabled": False}})
    session = open_session(settings.zenoh, "server", embedded=True)
    try:
        node = ServiceNode(settings, session)
        node.start()
        _feed(node, session, payloads[:5])
        assert node.stop_threads()  # three more frames arrive before the entities are undeclared
        for payload in payloads[5:8]:
            node.stats.count_received()
            node.submit(payload)
        node.stop()
        assert node.status()["frames_dropped"] == 3 and node.completed == node.stats.received == 8

        resumed = ServiceNode(settings, session).status()
        assert (resumed["frames_received"], resumed["frames_processed"], resumed["frames_dropped"]) == (8, 5, 3)
    finally:
        session.close()


def test_serve_resumes_after_sigterm_with_nothing_lost(router, tmp_path, reference):
    session, endpoint = router
    state, log = tmp_path / "state", tmp_path / "serve.log"
    serve = _serve(endpoint, state, log)
    try:
        _wait_for_service(session, "objslam/ptest/status")
        replay = _replay(endpoint, 90)
        assert replay.wait(timeout=120) == 0, replay.stdout.read()
        before = _wait_handled(session, 90, replay=replay)
        rows = _trajectory(session)
        loops = _get(session, "objslam/ptest/loops")["loops"]
        assert before["frames_processed"] == 90 and before["persistence"]["snapshots_written"] >= 1
        save = _objslam(
            "save",
            "--mode",
            "client",
            "--connect",
            endpoint,
            "--robot",
            "ptest",
            "--json",
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        out, err = save.communicate(timeout=120)
        assert save.returncode == 0 and json.loads(out)["frames_processed"] == 90, err
        assert len(np.loadtxt(state / "trajectory.tum", ndmin=2)) == 90 and (state / "map.png").is_file()
        (state / "trajectory.tum").unlink()  # the shutdown writes it again
    finally:
        assert _stop(serve) == 0, log.read_text()
    assert (state / "trajectory.tum").is_file() and (state / "map.db").is_file()

    serve = _serve(endpoint, state, log)
    try:
        after = _wait_for_service(session, "objslam/ptest/status")
        assert after["persistence"]["resumed_from"]["frames_processed"] == 90
        assert after["frames_processed"] == 90 and after["keyframes"] == before["keyframes"]
        assert after["frames_received"] == 90 and after["persistence"]["skipped_snapshots"] == []
        assert np.array_equal(_trajectory(session), rows)  # exactly, through JSON
        assert _get(session, "objslam/ptest/loops")["loops"] == loops
        _same_poses(rows, reference["after"][90])

        replay = _replay(endpoint, FRAMES)  # the client starts over: frames already mapped are rejected
        assert replay.wait(timeout=120) == 0, replay.stdout.read()
        final = _wait_handled(session, 90 + FRAMES, replay=replay)
        assert final["frames_processed"] == FRAMES
        assert final["frames_rejected"] == {"duplicate_timestamp": 1, "out_of_order": 89}
        _same_poses(_trajectory(session), reference["after"][FRAMES])
        assert _get(session, "objslam/ptest/loops")["loops"] == reference["loops"]
    finally:
        assert _stop(serve) == 0, log.read_text()


@pytest.mark.integration
def test_serve_killed_mid_run_loses_at_most_n_keyframes_and_keeps_the_prefix(router, tmp_path, reference):
    session, endpoint = router
    state, log = tmp_path / "state", tmp_path / "serve.log"
    serve = _serve(endpoint, state, log)
    replay = None
    try:
        _wait_for_service(session, "objslam/ptest/status")
        replay = _replay(endpoint, FRAMES, rate=12)
        seen = {}
        for _ in range(1200):
            seen = _get(session, "objslam/ptest/status") or seen
            if seen.get("keyframes", 0) >= 23:  # mid-run, between two snapshots (every 5 keyframes)
                break
            time.sleep(0.05)
        serve.kill()  # SIGKILL: no chance to write anything more
        serve.wait(timeout=30)
    finally:
        if serve.poll() is None:
            serve.kill()
        if replay is not None:
            replay.kill()
            replay.wait()
    assert seen["keyframes"] >= 23 and seen["frames_processed"] < FRAMES

    serve = _serve(endpoint, state, log)
    try:
        after = _wait_for_service(session, "objslam/ptest/status")
        resumed = after["persistence"]["resumed_from"]
        m = resumed["frames_processed"]
        assert after["keyframes"] == resumed["keyframes"]
        assert seen["keyframes"] - after["keyframes"] <= EVERY + MAPPING_LAG  # checkpoints wait for idle mapping
        assert after["frames_processed"] == m and reference["keyframes"][m] == resumed["keyframes"]
        _same_poses(_trajectory(session), reference["after"][m])  # the prefix, exactly

        replay = _replay(endpoint, FRAMES)
        assert replay.wait(timeout=120) == 0, replay.stdout.read()
        final = _wait_handled(session, after["frames_received"] + FRAMES, replay=replay)
        assert final["frames_processed"] == FRAMES
        _same_poses(_trajectory(session), reference["after"][FRAMES])
    finally:
        assert _stop(serve) == 0, log.read_text()
