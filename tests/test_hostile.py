"""Hostile input (issue 26): crafted frames, poisoned streams and crafted state files must not take the map over."""

from __future__ import annotations

import numpy as np
import pytest

from graph.geometry import pose_from_tum
from perception.frame import FrameRejected
from service.config import load_settings
from slam.build import build_core
from sources import open_dataset


def _ate(core, dataset) -> float:
    """RMS position error after a rigid alignment of the recorded trajectory to the ground truth."""
    traj = core.trajectory()
    index = {t: i for i, t in enumerate(dataset.ground_truth.timestamps)}
    est = traj.poses[:, :3, 3]
    gt = np.array([dataset.ground_truth.poses[index[t]][:3, 3] for t in traj.timestamps])
    mu_e, mu_g = est.mean(0), gt.mean(0)
    u, _, vt = np.linalg.svd((est - mu_e).T @ (gt - mu_g))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return float(np.sqrt(np.mean(np.sum((est - mu_e) @ r.T + mu_g - gt, axis=1) ** 2)))


# ---------------------------------------------------------------- the odometry source, per frame


def _run(frames, settings=None):
    core = build_core(load_settings(None, settings or {"loops": {"source": "off"}}))
    rejected = []
    for frame in frames:
        try:
            core.step(frame)
        except FrameRejected as exc:
            rejected.append(exc.reason.value)
    core.flush()
    return core, rejected


def test_one_crafted_frame_with_odometry_does_not_lock_a_visual_stream():
    """The first frame carries odometry 50 m away; every later frame has none (the robot tracks visually)."""
    ds = open_dataset("synthetic:room?seed=3&frames=40")
    frames = []
    for i in range(len(ds)):
        frame = ds.frame(i)
        frame.odometry = pose_from_tum(np.array([50.0, 0, 0, 0, 0, 0, 1.0])) if i == 0 else None
        frames.append(frame)
    core, rejected = _run(frames)
    assert rejected == []
    assert len(core.records) == len(ds)
    assert core.methods["features"] >= len(ds) - 5
    assert _ate(core, ds) < 0.05


def test_a_stream_whose_odometry_drops_out_is_tracked_visually_meanwhile():
    ds = open_dataset("synthetic:room?seed=4&frames=40")
    frames = []
    for i in range(len(ds)):
        frame = ds.frame(i)
        if 15 <= i < 25:
            frame.odometry = None
        frames.append(frame)
    core, rejected = _run(frames, {})
    assert rejected == []
    assert core.methods["odometry"] >= 25 and core.methods["odometry"] + core.methods["features"] >= 35
    assert _ate(core, ds) < 0.10


def test_without_visual_odometry_frames_without_odometry_are_rejected_and_counted():
    ds = open_dataset("synthetic:room?seed=4&frames=12")
    frames = []
    for i in range(len(ds)):
        frame = ds.frame(i)
        if i in (5, 6):
            frame.odometry = None
        frames.append(frame)
    core, rejected = _run(frames, {"loops": {"source": "off"}, "odometry": {"visual": False}})
    assert rejected == ["no_odometry", "no_odometry"]
    assert core.methods["odometry"] == 10


# ---------------------------------------------------------------- timestamps


def test_one_frame_stamped_far_ahead_is_rejected_and_never_becomes_the_reference():
    ds = open_dataset("synthetic:room?seed=5&frames=20")
    frames = [ds.frame(i) for i in range(len(ds))]
    for f in frames:
        f.odometry = None
    poison = ds.frame(10)
    poison.timestamp, poison.odometry = 1e15, None
    core, rejected = _run([*frames[:10], poison, *frames[10:]])
    assert rejected == ["time_jump"]
    assert len(core.records) == 20 and core.clock.resets == 0


def test_a_jump_with_matching_odometry_is_rejected_too():
    ds = open_dataset("synthetic:room?seed=5&frames=12")
    frames = [ds.frame(i) for i in range(len(ds))]
    jumped = ds.frame(11)
    jumped.timestamp += 5000.0
    jumped.odometry = jumped.odometry @ pose_from_tum(np.array([0.0, 0, 5000.0 * 9.0, 0, 0, 0, 1]))
    core, rejected = _run([*frames[:11], jumped])
    assert rejected == ["time_jump"] and len(core.records) == 11


def test_a_clock_that_really_jumped_starts_a_new_reference_after_consistent_frames():
    ds = open_dataset("synthetic:room?seed=5&frames=30")
    frames = [ds.frame(i) for i in range(len(ds))]
    for f in frames:
        f.odometry = None
    for f in frames[15:]:
        f.timestamp += 3600.0  # the robot's clock was set an hour ahead
    core, rejected = _run(frames)
    assert rejected == ["time_jump", "time_jump"]  # the third consistent frame starts the new reference
    assert len(core.records) == 28 and core.clock.resets == 1
    assert core.records[-1].timestamp == frames[-1].timestamp


# ---------------------------------------------------------------- a state directory that cannot run code


def _payload_of(stream: bytes) -> list[memoryview]:
    """A snapshot payload (buffer table + pickle stream, no out-of-band buffers) around a raw pickle stream."""
    from service.persistence import TABLE

    return [memoryview(TABLE.pack(len(stream), 0)), memoryview(stream)]


def _global(module: str, name: str) -> bytes:
    import pickle

    def text(s: str) -> bytes:
        b = s.encode()
        return pickle.SHORT_BINUNICODE + bytes([len(b)]) + b

    return text(module) + text(name) + pickle.STACK_GLOBAL


def _call(callable_: bytes, arg: str) -> bytes:
    import pickle

    b = arg.encode()
    return callable_ + pickle.BINUNICODE + len(b).to_bytes(4, "little") + b + pickle.TUPLE1 + pickle.REDUCE


CRAFTED = {
    # protocol 4 walks dotted names: numpy.dtypes -> its __builtins__ dict -> .get("eval") -> eval(...)
    "dotted_builtins": lambda code: _call(_call(_global("numpy.dtypes", "__builtins__.get"), "eval"), code),
    "dotted_own_package": lambda code: _call(_call(_global("slam.records", "np.__builtins__.get"), "eval"), code),
    "builtins_eval": lambda code: _call(_global("builtins", "eval"), code),
    "os_system": lambda code: _call(_global("os", "system"), f'python3 -c "{code}"'),
    "unloaded_own_module": lambda code: _call(_global("service.cli", "main"), code),
    "private_numpy_name": lambda code: _call(_global("numpy.dtypes", "_add_dtype_helper"), code),
}


@pytest.mark.parametrize("attack", sorted(CRAFTED))
def test_a_crafted_snapshot_is_refused_without_running_code(tmp_path, attack):
    import pickle

    from service.persistence import Persistence, SnapshotStore

    marker = tmp_path / "pwned"
    code = f"__import__('pathlib').Path({str(marker)!r}).write_text('x')"
    stream = pickle.PROTO + b"\x04" + CRAFTED[attack](code) + pickle.STOP
    store = SnapshotStore(tmp_path / "state" / "snapshots")
    store.write(_payload_of(stream))
    restored = []
    persistence = Persistence(tmp_path / "state", "robot1", 10, 3)
    persistence.resume(restored.append)
    assert not marker.exists()
    assert restored == []  # nothing usable: a new map
    assert persistence.status()["skipped_snapshots"][0]["reason"].startswith("snapshot refers to")
