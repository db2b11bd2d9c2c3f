"""The map store: exact resume through it, RAM that holds only the newest cold rows, SIGKILL at any moment,
corrupt and truncated files, a newer schema, and a state directory of the snapshot release migrated."""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from evaluation.trajectory_metrics import umeyama
from loops.archive import RESIDENT, ColdLog
from service.config import load_settings
from service.map_persistence import Persistence, service_state
from service.map_store import SCHEMA_VERSION, MapStore, StoreError
from service.persistence import SnapshotStore, decode, encode
from service.store_rows import tail
from slam.build import build_core
from slam.parts import COLD, CoreParts, assemble, core_parts
from slam.pose_log import PlacedPoses, replayed
from slam.snapshot import core_state, restore_core
from sources import open_dataset
from sources.base import truth_per_frame

SPEC = "synthetic:room?seed=0&frames=160&fps=10&width=320&height=240"
CUT = 110  # after the first loop closures, before the last ones


@pytest.fixture(scope="module")
def frames():
    ds = open_dataset(SPEC)
    return [ds.frame(i) for i in range(len(ds))]


@pytest.fixture(scope="module")
def reference(frames):
    """Trajectory after each frame of an uninterrupted run, and its map points at the end."""
    core = build_core(load_settings())
    after = []
    for frame in frames:
        core.step(frame)
        after.append(core.trajectory().poses)
    return {"after": after, "cloud": core.cloud()}


def _checkpointed(frames, path: Path, stop: int):
    """A core fed ``frames[:stop]`` with a checkpoint after every keyframe (and at the end), as serve does."""
    settings = load_settings()
    core, store = build_core(settings), MapStore(path, settings.robot, COLD)
    written = 0
    for i, frame in enumerate(frames[:stop]):
        core.step(frame)
        if core.graph.num_keyframes > written or i + 1 == stop:
            written = core.graph.num_keyframes
            parts = core_parts(core)
            store.checkpoint(parts.small, parts.logs, written, i + 1)
    return core, store


def test_a_core_resumed_from_the_store_continues_exactly_and_reads_spilled_features_back(tmp_path, frames, reference):
    core, store = _checkpointed(frames, tmp_path / "map.db", CUT)
    assert core.kf_points.resident == RESIDENT < len(core.kf_points)  # the rest is in the store only
    assert core.loops.keyframes.features.resident == RESIDENT < len(core.loops.keyframes)
    store.close()

    reader = MapStore(tmp_path / "map.db", "robot1", COLD)
    loaded = reader.load()
    assert loaded is not None and loaded.frames == CUT and reader.skipped == []
    features = loaded.logs["loops.keyframe_features"]
    assert isinstance(features, ColdLog) and features.resident == 0  # nothing of it read on restart
    restored = restore_core(load_settings(), assemble(CoreParts(loaded.small, loaded.logs), materialize=False))
    assert np.array_equal(restored.trajectory().poses, reference["after"][CUT - 1])
    for frame in frames[CUT:]:
        restored.step(frame)
    assert np.array_equal(restored.trajectory().poses, reference["after"][-1])  # loops to old keyframes read them
    assert restored.loops.keyframes.features.loads > 0
    assert np.array_equal(restored.cloud(), reference["cloud"])  # map points of every keyframe, read back


def test_checkpoint_work_follows_the_new_rows_not_the_map(tmp_path, frames):
    """Each log is written once: the rows stored equal the rows the core holds, and a checkpoint with nothing
    new writes only its small part."""
    core, store = _checkpointed(frames, tmp_path / "map.db", 80)
    for name, rows in core_parts(core).logs.items():
        state = store.logs[name]
        assert state.written == len(rows), name
    rows = store.db.execute("SELECT log, SUM(count) FROM chunks GROUP BY log").fetchall()
    stored = dict(rows)
    assert stored["records"] == len(core.records) and stored["graph.factors"] == len(core.graph.factors)
    before = store.bytes_written
    parts = core_parts(core)
    store.checkpoint(parts.small, parts.logs, core.graph.num_keyframes, 80)
    small = len(b"".join(encode(parts.small)))
    assert store.bytes_written - before == small


_KILLED_WRITER = """
import sys
from service.config import load_settings
from service.map_store import MapStore
from slam.build import build_core
from slam.parts import COLD, core_parts
from sources import open_dataset
from sources.base import truth_per_frame
from evaluation.trajectory_metrics import umeyama
settings = load_settings()
ds = open_dataset(sys.argv[2])
core, store = build_core(settings), MapStore(sys.argv[1], settings.robot, COLD)
loaded = store.load()
start = 0 if loaded is None else loaded.frames
if loaded is not None:
    from service.map_persistence import service_state
    from slam.parts import CoreParts, assemble
    from slam.snapshot import restore_core
    core = restore_core(settings, assemble(CoreParts(loaded.small, loaded.logs), materialize=False))
written = core.graph.num_keyframes
for i in range(start, len(ds)):
    core.step(ds.frame(i))
    if core.graph.num_keyframes > written:
        written = core.graph.num_keyframes
        parts = core_parts(core)
        store.checkpoint(parts.small, parts.logs, written, i + 1)
        print(written, i + 1, flush=True)
"""


def test_sigkill_at_random_moments_loses_at_most_the_last_keyframe_and_the_store_verifies(tmp_path):
    """A writer killed five times at random moments (mid-transaction most likely: it writes all the time),
    restarted on its store each time: every restart finds the newest committed checkpoint."""
    path, rng = tmp_path / "map.db", np.random.default_rng(7)
    spec = "synthetic:room?seed=1&frames=400&fps=10&width=160&height=120"
    committed = (0, 0)
    for _ in range(5):
        proc = subprocess.Popen(
            [sys.executable, "-c", _KILLED_WRITER, str(path), spec],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        lines = []
        deadline = time.monotonic() + 120
        target = len(lines) + int(rng.integers(3, 12))
        assert proc.stdout is not None
        while len(lines) < target and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
        time.sleep(float(rng.uniform(0.0, 0.2)))
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        lines += proc.stdout.readlines()  # printed (after their commit) before the kill
        assert lines, "the writer wrote no checkpoint"
        seen = tuple(int(x) for x in lines[-1].split())  # committed before it was printed
        assert seen[0] > committed[0]
        db = sqlite3.connect(path)
        assert db.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        db.close()
        loaded = MapStore(path, "robot1", COLD).load()
        assert loaded is not None
        assert seen[0] <= loaded.keyframes <= seen[0] + 1  # at most the one being written when killed is lost
        committed = (loaded.keyframes, loaded.frames)


def test_a_truncated_store_is_moved_aside_with_a_clear_error_and_a_new_map_begins(tmp_path, frames, caplog):
    _, store = _checkpointed(frames, tmp_path / "map.db", 40)
    store.db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    store.close()
    data = (tmp_path / "map.db").read_bytes()
    (tmp_path / "map.db").write_bytes(data[: len(data) // 3])  # pages lost from the middle on

    persistence = Persistence(tmp_path, "robot1")
    restored: list = []
    assert not persistence.resume(restored.append, service_state)
    skipped = persistence.status()["skipped_snapshots"]
    assert skipped and any("malformed" in s["reason"] or "rows" in s["reason"] for s in skipped), skipped
    assert restored == []
    assert persistence.save({"x": 1}, {}, 1, 1, wait=True)  # a usable store again


def _records_lengths(store: MapStore) -> list[int]:
    rows = store.db.execute("SELECT logs FROM checkpoints ORDER BY id DESC").fetchall()
    return [json.loads(text)["records"][1] for (text,) in rows]


def test_a_flipped_byte_in_a_log_falls_back_to_a_checkpoint_that_does_not_need_it(tmp_path, frames):
    core, store = _checkpointed(frames, tmp_path / "map.db", 60)
    for i in range(60, 80):  # until the newest records chunk is one only the newest checkpoint needs
        newest = store.db.execute("SELECT MAX(first) FROM chunks WHERE log = 'records'").fetchone()[0]
        if _records_lengths(store)[1] <= newest:
            break
        core.step(frames[i])
        parts = core_parts(core)
        store.checkpoint(parts.small, parts.logs, core.graph.num_keyframes, i + 1)
    lengths = _records_lengths(store)
    assert lengths[1] <= newest < lengths[0]
    key = ("records", newest)
    data = bytearray(store.db.execute("SELECT data FROM chunks WHERE log = ? AND first = ?", key).fetchone()[0])
    data[len(data) // 2] ^= 0x01
    store.db.execute("UPDATE chunks SET data = ? WHERE log = ? AND first = ?", (bytes(data), *key))
    store.close()
    reader = MapStore(tmp_path / "map.db", "robot1", COLD)
    loaded = reader.load()
    assert len(reader.skipped) == 1 and "checksum mismatch" in reader.skipped[0][1], reader.skipped
    assert loaded is not None and len(loaded.logs["records"]) == lengths[1]


def test_a_store_of_a_newer_schema_is_refused_with_what_to_do(tmp_path):
    MapStore(tmp_path / "map.db", "robot1").close()
    db = sqlite3.connect(tmp_path / "map.db")
    db.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'", (str(SCHEMA_VERSION + 1),))
    db.commit()
    db.close()
    with pytest.raises(StoreError, match="newer than this release"):
        MapStore(tmp_path / "map.db", "robot1")


def test_a_state_directory_of_the_snapshot_release_is_migrated_into_the_store(tmp_path, frames, reference):
    settings = load_settings()
    core = build_core(settings)
    for frame in frames[:CUT]:
        core.step(frame)
    old = {"robot": "robot1", "created": 0.0, "keyframes": core.graph.num_keyframes, "frames_processed": CUT}
    SnapshotStore(tmp_path / "snapshots").write(encode({**old, "state": {"pipeline": core_state(core)}}))

    def restore_into(box):
        return lambda state: box.append(restore_core(settings, state["pipeline"]))

    box: list = []
    persistence = Persistence(tmp_path, "robot1")
    assert persistence.resume(restore_into(box), service_state)
    assert persistence.status()["resumed_from"]["file"].startswith("snapshot-")
    migrated = box[0]
    parts = core_parts(migrated)
    assert persistence.save({"pipeline": parts.small}, parts.logs, migrated.graph.num_keyframes, CUT, wait=True)  # all

    again: list = []
    persistence = Persistence(tmp_path, "robot1")
    assert persistence.resume(restore_into(again), service_state)
    assert persistence.status()["resumed_from"]["file"].startswith("map.db#checkpoint-")
    assert np.array_equal(again[0].trajectory().poses, reference["after"][CUT - 1])


def test_a_second_session_started_elsewhere_relocalizes_and_maps_in_the_first_sessions_frame(tmp_path):
    """Session 1 maps the first two thirds of a lap; session 2 begins 1000 s later a lap on, at a place session
    1 saw: its first keyframe is relocalized against the stored ones and its poses lie in session 1's frame."""
    ds = open_dataset("synthetic:room?seed=0&frames=300&fps=10&width=320&height=240&revolutions=2")
    settings = load_settings()
    frames1 = [ds.frame(i) for i in range(100)]
    _, store = _checkpointed(frames1, tmp_path / "map.db", 100)
    store.close()

    persistence = Persistence(tmp_path, settings.robot)
    box: list = []
    assert persistence.resume(lambda state: box.append(restore_core(settings, state["pipeline"])), _core_only)
    core = box[0]
    core.begin_session(settings.persistence.session_gap_s)
    second = list(range(170, 230))
    for i in second:
        frame = ds.frame(i)
        core.step(replace(frame, timestamp=frame.timestamp + 1000.0))
    status = persistence.status(core)["session"]
    assert status["first_keyframe"] is not None and status["localized"], status
    assert status["against_keyframe"] is not None and status["against_keyframe"] < status["first_keyframe"]

    truth = truth_per_frame(ds)
    poses = core.trajectory(tied_only=True)
    times = np.round(poses.timestamps, 6)
    first = {round(float(f.timestamp), 6) for f in frames1}
    one = np.array([t in first for t in times])
    assert one.sum() == 100 and (~one).sum() == len(second)  # every frame of both sessions is in the map
    T = umeyama(poses.poses[one, :3, 3], truth[:100, :3, 3])  # session 1's frame -> the true world
    p2 = poses.poses[~one, :3, 3] @ T[:3, :3].T + T[:3, 3]
    errors = np.linalg.norm(p2 - truth[second, :3, 3], axis=1)
    assert np.median(errors) < 0.05, errors


def _core_only(small, logs):
    """A checkpoint written by ``_checkpointed`` (the core's parts alone) as ``Persistence.resume`` gives it."""
    return {"pipeline": assemble(CoreParts(small, logs), materialize=False)}


def test_chunks_merge_up_to_the_top_level_and_read_back_whole(tmp_path):
    """600 checkpoints of one row each: merged 16 at a time, never above level 2 (a merge re-encodes at most
    256 checkpoints' rows), about n / 256 + 32 chunks, and every row back in order; a replaced container is a
    new generation written whole, the old one deleted once no kept checkpoint needs it."""
    store = MapStore(tmp_path / "map.db", "robot1")
    rows: list[int] = []
    for i in range(600):
        rows.append(i)
        store.checkpoint({"i": i}, {"rows": rows}, i, i)
    levels = store.db.execute("SELECT level, COUNT(*) FROM chunks WHERE log = 'rows' GROUP BY level").fetchall()
    assert max(level for level, _ in levels) == 2
    assert sum(n for _, n in levels) <= 600 // 256 + 32
    loaded = MapStore(tmp_path / "map.db", "robot1").load()
    assert loaded is not None and loaded.logs["rows"] == list(range(600)) and loaded.small == {"i": 599}

    replaced = [-1, -2]
    for i in range(4):  # keep = 3: the old generation outlives three checkpoints
        store.checkpoint({"i": 600 + i}, {"rows": replaced}, 600, 600)
    generations = store.db.execute("SELECT DISTINCT generation FROM chunks WHERE log = 'rows'").fetchall()
    assert generations == [(1,)]
    loaded = MapStore(tmp_path / "map.db", "robot1").load()
    assert loaded is not None and loaded.logs["rows"] == [-1, -2]


def test_a_checkpoint_waiting_for_the_disk_does_not_hold_the_caller(tmp_path):
    """The rows are encoded by the caller and written by the store's writer thread: with the database locked by
    another connection the caller gets on at once, no second checkpoint starts while one is being written,
    and once the disk is free the checkpoint commits with the rows as they were when it was taken."""
    persistence = Persistence(tmp_path, "robot1", every_keyframes=1)
    rows = [np.arange(3) * i for i in range(50)]
    assert persistence.save({"n": 50}, {"rows": rows}, 1, 50, wait=True)
    other = sqlite3.connect(tmp_path / "map.db", isolation_level=None)
    other.execute("BEGIN IMMEDIATE")  # the write lock: the writer thread waits for it
    try:
        rows.append(np.arange(3) * 50)
        t0 = time.perf_counter()
        assert persistence.save({"n": 51}, {"rows": rows}, 2, 51)
        assert time.perf_counter() - t0 < 0.5
        rows.append(np.full(3, -1))  # a row after the checkpoint was taken: not in it
        time.sleep(0.3)
        assert persistence.writing and not persistence.due(3)
    finally:
        other.execute("ROLLBACK")
        other.close()
    assert persistence.settle() and not persistence.writing
    status = persistence.status()
    assert status["last_snapshot"]["keyframes"] == 2 and status["failed_writes"] == 0
    assert status["last_snapshot"]["write_ms"] >= 250  # it waited for the lock on the writer thread
    loaded = MapStore(tmp_path / "map.db", "robot1").load()
    assert loaded is not None and loaded.small == {"n": 51} and len(loaded.logs["rows"]) == 51
    assert np.array_equal(loaded.logs["rows"][50], np.arange(3) * 50)
    persistence.close()


def test_a_failed_checkpoint_leaves_the_writer_as_before_and_the_next_one_writes_its_rows(tmp_path):
    """A transaction that fails half-way (the disk full) is rolled back; the writer's books of chunks too, so
    the next checkpoint writes every row since the last good one, merges included."""
    store = MapStore(tmp_path / "map.db", "robot1")
    rows: list[bytes] = []
    for i in range(20):
        rows.append(bytes(100))
        store.checkpoint({}, {"rows": rows}, i, i)
    pages = store.db.execute("PRAGMA page_count").fetchone()[0]
    store.db.execute(f"PRAGMA max_page_count = {pages}")
    rows.extend(bytes(4000) for _ in range(12))  # completes 16 chunks: a merge in the failing transaction
    with pytest.raises(sqlite3.Error):
        store.checkpoint({}, {"rows": rows}, 20, 20)
    store.db.execute("PRAGMA max_page_count = 1073741823")
    for i in range(21, 300):  # merges of every level on the books as they were before the failure
        store.checkpoint({}, {"rows": rows}, i, i)
        rows.append(bytes(10))
    loaded = MapStore(tmp_path / "map.db", "robot1").load()
    assert loaded is not None and loaded.logs["rows"] == rows[:-1]


def test_a_replaced_container_is_written_whole_even_where_the_old_one_lived(tmp_path):
    """The writer holds the container it wrote from: a new one (a window roll's array) never passes for it,
    even allocated where a freed one was."""
    store = MapStore(tmp_path / "map.db", "robot1")
    for i in range(50):  # every checkpoint a new array, as a roll gives; the last one freed before it is made
        store.checkpoint({}, {"fixed": np.full((i + 1, 2), float(i))}, i, i)
    loaded = MapStore(tmp_path / "map.db", "robot1").load()
    assert loaded is not None and np.array_equal(loaded.logs["fixed"], np.full((50, 2), 49.0))


def test_a_rolling_window_resumes_exactly_from_the_store_and_checkpoints_stay_the_same_size(tmp_path, frames):
    """A window of 12 keyframes rolling every 4 (rebuilt many times, landmarks frozen and revived, a child
    process solving the whole graph): restored from the store it is the live core exactly and continues like
    it, and a checkpoint's own writes do not grow as the map does (the window's books are logs too)."""
    settings = load_settings(None, {"graph": {"window_keyframes": 12, "window_step": 4}})
    core, store = build_core(settings), MapStore(tmp_path / "map.db", settings.robot, COLD)
    written, sizes = 0, []
    for i, frame in enumerate(frames[:CUT]):
        core.step(frame)
        if core.graph.num_keyframes > written:
            written, before = core.graph.num_keyframes, store.bytes_written
            parts = core_parts(core)
            store.checkpoint(parts.small, parts.logs, written, i + 1)
            sizes.append(store.bytes_written - before)
    parts = core_parts(core)
    store.checkpoint(parts.small, parts.logs, core.graph.num_keyframes, CUT)
    assert core.graph.rebuilt and core.graph.start > 20
    early, late = np.median(sizes[10:20]), np.median(sizes[-10:])
    assert late < 1.3 * early, (early, late)

    loaded = MapStore(tmp_path / "map.db", settings.robot, COLD).load()  # the live core reads from ``store``
    assert loaded is not None
    restored = restore_core(settings, assemble(CoreParts(loaded.small, loaded.logs), materialize=False))
    assert np.array_equal(restored.graph.poses(), core.graph.poses())
    for frame in frames[CUT:]:
        core.step(frame)
        restored.step(frame)
    # a rolled window re-anchors at the whole-graph solves of its child process as they come back, and a
    # restored child first replays the history: which solve a roll gets depends on timing (two live runs of
    # these frames differ by micrometres, a restored one by millimetres), so the runs agree to 1 cm, not bit
    # for bit (a window restored wrong is decimetres off, or fails)
    np.testing.assert_allclose(restored.trajectory().poses[:, :3, 3], core.trajectory().poses[:, :3, 3], atol=0.01)
    core.close()
    restored.close()
    store.close()


def test_a_long_chunk_of_frozen_records_is_encoded_by_the_writer_and_reads_back_the_same(tmp_path):
    """Rows nothing changes (frozen dataclasses) are encoded when written, not when staged; what reads back is
    what the checkpoint took, and small chunks and other rows are encoded at once."""
    from graph.factors import FactorRecord
    from service.store_rows import PIECE_ROWS, FrozenRows, Pieces

    rng = np.random.default_rng(3)
    factors = [FactorRecord(i, i + 1, rng.normal(size=(4, 4)), 0.01, 0.02) for i in range(300)]
    store = MapStore(tmp_path / "map.db", "robot1")
    staged = store.stage({"n": 300}, {"factors": factors, "ids": list(range(300))}, 1, 1)
    blobs = {p[0]: p[-1] for _, p in staged.ops}
    assert isinstance(blobs["factors"], FrozenRows) and isinstance(blobs["ids"], bytes)
    taken = list(factors)
    del factors[10:]  # the caller goes on with its log; the staged rows are a list of their own
    store.write(staged)
    loaded = MapStore(tmp_path / "map.db", "robot1").load()
    assert loaded is not None and len(loaded.logs["factors"]) == 300
    assert all(np.array_equal(a.measurement, b.measurement) for a, b in zip(loaded.logs["factors"], taken, strict=True))
    assert not FrozenRows.admits([replace(factors[0])] * 10) and not FrozenRows.admits(list(range(300)))
    # encoded piece by piece (the writer thread lets the worker run between pieces), read back as one list
    (data,) = store.db.execute("SELECT data FROM chunks WHERE log = 'factors'").fetchone()
    pieces = decode(bytearray(data))
    assert isinstance(pieces, Pieces) and len(pieces.payloads) == -(-300 // PIECE_ROWS)


@given(st.integers(0, 40), st.integers(0, 60), st.one_of(st.none(), st.integers(0, 60)))
def test_the_rows_of_a_dict_log_are_its_items_in_order_whichever_end_they_are_taken_from(n, start, stop):
    rows = {(i, -i): np.full(2, i) for i in range(n)}
    expected = list(rows.items())[start:stop]
    got = tail(rows, start, stop)
    assert [k for k, _ in got] == [k for k, _ in expected] and len(got) == len(expected)
    assert all(a is b for (_, a), (_, b) in zip(got, expected, strict=True))


@given(st.lists(st.tuples(st.integers(0, 3), st.floats(0, 1)), max_size=40), st.integers(0, 2**31))
def test_placed_poses_log_only_their_revisions_and_replay_to_the_poses(steps, seed):
    """Appends and revisions of a few or of most poses: the revision log replays to the poses, its rows beyond
    the poses are the poses that changed, and it stays within twice the poses (plus a margin)."""
    rng = np.random.default_rng(seed)
    placed = PlacedPoses()
    for appended, share in steps:
        for _ in range(appended):
            placed.append(rng.normal(size=(4, 4)))
        poses = placed.rows().copy()
        changed = rng.random(len(poses)) < share
        poses[changed] += 1.0
        before = placed.revisions().copy()
        placed.revise(poses)
        assert np.array_equal(placed.rows(), poses)
        log, c = placed.revisions(), int(changed.sum())
        if 2 * c <= len(poses) and len(before) + c <= 2 * len(poses) + 64:  # the changed poses appended
            assert np.array_equal(log[: len(before)], before) and len(log) == len(before) + c
            assert np.array_equal(log[len(before) :, 0], np.flatnonzero(changed))
        else:  # begun again from the poses
            assert np.array_equal(log[:, 0], np.arange(len(poses)))
        assert len(log) <= 2 * len(poses) + 64
        assert np.array_equal(replayed(log), poses)
        assert np.array_equal(PlacedPoses(revisions=log).rows(), poses)
    with pytest.raises(ValueError):
        placed.revise(np.zeros((len(placed) + 1, 4, 4)))


def test_a_store_with_object_poses_written_whole_still_restores_them(tmp_path, frames):
    """Stores written before 2026-12-04 hold ``object_poses`` (every pose at every re-placement); they read back
    into the same poses, and the next checkpoint logs revisions."""
    core, store = _checkpointed(frames, tmp_path / "map.db", 80)
    assert core.reposes > 0 and len(core.object_poses) > 0
    parts = core_parts(core)
    logs = dict(parts.logs)
    del logs["object_pose_revisions"]
    logs["object_poses"] = core.object_poses.rows()
    store.checkpoint(parts.small, logs, core.graph.num_keyframes, 80)
    store.close()
    reader = MapStore(tmp_path / "map.db", "robot1", COLD)
    loaded = reader.load()
    assert loaded is not None and "object_pose_revisions" not in loaded.logs
    restored = restore_core(load_settings(), assemble(CoreParts(loaded.small, loaded.logs), materialize=False))
    assert np.array_equal(restored.object_poses.rows(), core.object_poses.rows())
    again = core_parts(restored)
    reader.checkpoint(again.small, again.logs, core.graph.num_keyframes, 80)
    assert reader.logs["object_pose_revisions"].written == len(core.object_poses)


def test_a_whole_graph_solve_re_places_only_the_keyframes_it_moved_so_the_store_writes_only_those():
    """After a loop closure's whole-graph solve every keyframe's pose changes a little (here 0.1 mm and 0.001
    degrees) and a stretch of them by centimetres: only that stretch is re-placed and logged, not every pose,
    which the store would write again at every re-placement (work that grows with the map)."""
    from scipy.spatial.transform import Rotation

    from slam.repose import moved_only
    from slam.settings import ObjectSettings

    rng = np.random.default_rng(3)
    n = 400
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 3] = rng.normal(size=(n, 3))
    placed = PlacedPoses(poses)
    now = poses.copy()
    now[:, :3, 3] += 1e-4
    now[:, :3, :3] = Rotation.from_euler("z", 0.001, degrees=True).as_matrix() @ now[:, :3, :3]
    now[300:340, :3, 3] += 0.03  # the stretch the loop closure corrected
    now[350, :3, :3] = Rotation.from_euler("x", 0.2, degrees=True).as_matrix() @ now[350, :3, :3]  # a turn alone
    cfg = ObjectSettings()
    chosen = moved_only(now, placed.rows(), cfg)
    moved = np.flatnonzero((chosen != poses).reshape(n, 16).any(axis=1))
    assert moved.tolist() == [*range(300, 340), 350]
    assert np.array_equal(chosen[moved], now[moved])
    before = len(placed.revisions())
    placed.revise(chosen)
    assert len(placed.revisions()) == before + len(moved)  # appended, not begun again with every pose
    assert np.abs(chosen - now)[:, :3, 3].max() <= 0.1 * cfg.repose_m + 1e-12  # the others are as good as now
