"""Map store cost against map size: a checkpoint per keyframe (new rows + the small part), load and restore.

The pipeline runs in-process on a synthetic scene with the service defaults (appearance loop closure,
objects) and checkpoints a map store (``service.map_store``) after every keyframe, as ``serve --state-dir``
does; at each row the store is opened anew, its newest checkpoint loaded and a core restored from it.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from bench.report import markdown_table, record, show_table
from service.config import load_settings
from service.map_store import MapStore
from slam.build import build_core
from slam.parts import COLD, CoreParts, assemble, core_parts
from slam.snapshot import restore_core
from sources import open_dataset

HEADER = [
    "keyframes",
    "frames",
    "loops accepted",
    "store MB",
    "checkpoint ms p50",
    "checkpoint ms max",
    "load ms",
    "restore ms",
    "restored = saved",
]
WINDOW = 50  # checkpoint times over the last this many keyframes before each row


def measure(dataset: str, checkpoints: list[int]) -> list[list[object]]:
    """One row per checkpoint (number of keyframes) reached while processing ``dataset``."""
    settings = load_settings()
    data = open_dataset(dataset)
    pipeline = build_core(settings)
    rows: list[list[object]] = []
    todo, times = sorted(checkpoints), []
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "map.db"
        store = MapStore(path, settings.robot, COLD)
        written = 0
        for i in range(len(data)):
            pipeline.step(data.frame(i))
            keyframes = pipeline.graph.num_keyframes
            if keyframes > written:
                t0 = time.perf_counter()
                parts = core_parts(pipeline)
                store.checkpoint(parts.small, parts.logs, keyframes, i + 1)
                times.append(time.perf_counter() - t0)
                written = keyframes
            if not todo or keyframes < todo[0]:
                continue
            todo.pop(0)
            rows.append(_row(settings, pipeline, path, i + 1, times[-WINDOW:]))
            if not todo:
                break
        store.close()
    return rows


def _row(settings, pipeline, path: Path, frames: int, times: list[float]) -> list[object]:
    t0 = time.perf_counter()
    reader = MapStore(path, settings.robot, COLD)
    loaded = reader.load()
    t1 = time.perf_counter()
    assert loaded is not None
    restored = restore_core(settings, assemble(CoreParts(loaded.small, loaded.logs)))
    t2 = time.perf_counter()
    reader.close()
    same = bool(
        np.array_equal(restored.trajectory().poses[: loaded.frames], pipeline.trajectory().poses[: loaded.frames])
    )
    restored.close()
    loops = pipeline.loops.n_accepted if pipeline.loops is not None else 0
    size = sum(p.stat().st_size for p in path.parent.glob("map.db*")) / 1e6
    ms = [round(float(np.median(times)) * 1e3, 1), round(max(times) * 1e3, 1), round((t1 - t0) * 1e3, 1)]
    return [pipeline.graph.num_keyframes, frames, loops, round(size, 1), *ms, round((t2 - t1) * 1e3, 1), same]


def run_persistence_bench(console, dataset: str, checkpoints: list[int], write: Path | None) -> None:
    rows = measure(dataset, checkpoints)
    show_table(console, "Map store cost against map size", HEADER, rows)
    if write is not None:
        notes = (
            f"A checkpoint after every keyframe (`persistence.every_keyframes` 1), as `serve --state-dir` writes "
            f"them; its time (p50 and max over the last {WINDOW} keyframes) is the core's parts taken, the new "
            "rows and the small part encoded, and one SQLite transaction (WAL, synchronous=NORMAL). Load opens "
            "the store and reads the newest checkpoint (cold logs included); restore replays the window's iSAM2 "
            "log and rebuilds the ORB extractor and matcher. `objslam bench longrun` follows this to 20,000 "
            "keyframes."
        )
        cmd = f"objslam bench persistence --dataset '{dataset}' --keyframes {','.join(map(str, checkpoints))}"
        record("persistence", "Map store checkpoint and resume cost", cmd, markdown_table(HEADER, rows), notes, write)
