"""Snapshot cost against map size: capture (state + pickle), write (checksum, fsync, rename), load, restore.

The pipeline runs in-process on a synthetic scene with the service defaults (appearance loop closure,
objects); at each checkpoint its state is captured, written to a temporary state directory, read back and
restored, as ``serve --state-dir`` does.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from bench.report import markdown_table, record, show_table
from service.config import load_settings
from service.persistence import Persistence
from slam.build import build_core
from slam.core import SlamCore
from slam.snapshot import core_state, restore_core
from sources import open_dataset

HEADER = [
    "keyframes",
    "frames",
    "loops accepted",
    "snapshot MB",
    "state() ms",
    "capture ms",
    "write ms",
    "load ms",
    "restore ms",
    "restored = saved",
]
REPEATS = 5  # medians of this many captures and writes, and of REPEATS // 2 loads and restores


def measure(dataset: str, checkpoints: list[int]) -> list[list[object]]:
    """One row per checkpoint (number of keyframes) reached while processing ``dataset``."""
    settings = load_settings()
    data = open_dataset(dataset)
    pipeline = build_core(settings)
    rows: list[list[object]] = []
    todo = sorted(checkpoints)
    with tempfile.TemporaryDirectory() as tmp:
        store = Persistence(Path(tmp), settings.robot)
        for i in range(len(data)):
            pipeline.step(data.frame(i))
            if not todo or pipeline.graph.num_keyframes < todo[0]:
                continue
            todo.pop(0)
            rows.append(_checkpoint(settings, pipeline, store, i + 1))
            if not todo:
                break
    return rows


def _checkpoint(settings, pipeline: SlamCore, store: Persistence, frames: int) -> list[object]:
    keyframes = pipeline.graph.num_keyframes
    state_s, capture_s, write_s, load_s, restore_s = [], [], [], [], []
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        state = {"pipeline": core_state(pipeline)}
        t1 = time.perf_counter()
        payload = store.capture(keyframes, frames, state)
        t2 = time.perf_counter()
        written = store.save(payload, keyframes, frames, t2 - t0)
        if written is None:
            raise RuntimeError(f"could not write a snapshot in {store.store.directory} (the log says why)")
        state_s.append(t1 - t0)
        capture_s.append(t2 - t0)
        write_s.append(written.write_s)
        size_mb = round(written.size / 1e6, 1)
    for _ in range(max(1, REPEATS // 2)):
        t0 = time.perf_counter()
        snap = next(store.store.candidates([]))[1]
        t1 = time.perf_counter()
        restored = restore_core(settings, snap["state"]["pipeline"])
        load_s.append(t1 - t0)
        restore_s.append(time.perf_counter() - t1)
    same = bool(np.array_equal(restored.trajectory().poses, pipeline.trajectory().poses))
    loops = pipeline.loops.n_accepted if pipeline.loops is not None else 0
    ms = [round(float(np.median(v)) * 1e3, 1) for v in (state_s, capture_s, write_s, load_s, restore_s)]
    return [keyframes, frames, loops, size_mb, *ms, same]


def run_persistence_bench(console, dataset: str, checkpoints: list[int], write: Path | None) -> None:
    rows = measure(dataset, checkpoints)
    show_table(console, "Snapshot cost against map size", HEADER, rows)
    if write is not None:
        notes = (
            f"Medians of {REPEATS} captures and writes. In `serve --state-dir` the worker thread captures "
            "(`state()` under the pipeline lock, so queries wait for that part only, then pickling) and writes "
            "(SHA-256, write, fsync, rename, directory fsync); capture + write is the worker's stall every "
            "`persistence.every_keyframes` keyframes (default 10). Load (read, SHA-256, restricted unpickle) "
            "and restore (replaying the iSAM2 update log, rebuilding the ORB extractor and matcher) happen "
            "once, on start. Most of the size is the ORB features of every keyframe that loop closure keeps "
            "(~0.1 MB each), so size and capture time grow linearly with the map."
        )
        cmd = f"objslam bench persistence --dataset '{dataset}' --keyframes {','.join(map(str, checkpoints))}"
        record("persistence", "Snapshot write and resume cost", cmd, markdown_table(HEADER, rows), notes, write)
