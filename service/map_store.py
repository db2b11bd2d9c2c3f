"""The map store: one SQLite database in the state directory (``map.db``), written a little at every keyframe.

What it holds (schema ``SCHEMA_VERSION``, ``meta.schema_version``; ``MIGRATIONS`` bring older stores up):

- ``chunks``: the rows of the SLAM core's append-only logs (``slam.parts``), a chunk per checkpoint with the
  rows new since the previous one. Trailing chunks are merged ``FANOUT`` at a time into one of the next level
  up to ``TOP_LEVEL`` (re-encoded from the live log, no read; so a merge never re-encodes more than
  ``FANOUT ** TOP_LEVEL`` checkpoints' rows), and a log of n checkpoints is about n / 256 + 32 chunks.
- ``cold``: the cold logs' rows (``slam.parts.COLD``: loop-closure features, map points), one per keyframe,
  never merged and read back one by one, on demand.
- ``checkpoints``: per checkpoint, the length and generation of every log, and the small part of the state.
  A log whose container was replaced (a window roll) starts a new generation, written whole.
- ``sessions``: one row per run of the service on this map.

A checkpoint is one transaction: its new chunks, cold rows and the checkpoint row commit together or not at
all (WAL mode, ``synchronous=NORMAL``: a killed process loses nothing committed). Every blob carries its
SHA-256; a checkpoint is used only when its blob and every chunk it needs verify, else the one before it.
Blobs are ``service.persistence.encode`` payloads, read with its plain-data unpickler.
"""

from __future__ import annotations

import hashlib
import json
import logging
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

from loops.archive import ColdLog
from service.persistence import encode
from service.store_rows import (
    CHUNK,
    COLD_ROW,
    DELETE_CHUNKS,
    FrozenRows,
    Loaded,
    LogState,
    Staged,
    StoreError,
    join,
    kind_of,
    owner,
    tail,
    unblob,
)

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
FANOUT = 16  # trailing chunks of one level merged into one of the next
TOP_LEVEL = 2  # chunks of FANOUT**2 checkpoints are not merged further: a merge re-encodes at most that many
SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS sessions (
    id INTEGER PRIMARY KEY, started REAL NOT NULL, robot TEXT NOT NULL, info TEXT NOT NULL DEFAULT '{}');
CREATE TABLE IF NOT EXISTS checkpoints (
    id INTEGER PRIMARY KEY, session INTEGER NOT NULL, created REAL NOT NULL, keyframes INTEGER NOT NULL,
    frames INTEGER NOT NULL, logs TEXT NOT NULL, small BLOB NOT NULL, sha BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS chunks (
    log TEXT NOT NULL, generation INTEGER NOT NULL, first INTEGER NOT NULL, count INTEGER NOT NULL,
    level INTEGER NOT NULL, data BLOB NOT NULL, sha BLOB NOT NULL, PRIMARY KEY (log, generation, first));
CREATE TABLE IF NOT EXISTS cold (
    log TEXT NOT NULL, generation INTEGER NOT NULL, idx INTEGER NOT NULL, data BLOB NOT NULL,
    sha BLOB NOT NULL, PRIMARY KEY (log, generation, idx));
"""
MIGRATIONS: dict[int, Callable[[sqlite3.Connection], None]] = {}
"""Schema version -> the step that brings a store of that version to the next (none yet: version 1 is the
first; a store without ``meta.schema_version`` is version 0, an empty file)."""


class MapStore:
    """The ``map.db`` of a state directory (see the module docstring); single writer, this process."""

    def __init__(self, path: Path, robot: str, cold: frozenset[str] = frozenset(), keep: int = 3):
        if keep < 2:
            raise ValueError("keep at least two checkpoints, so a bad newest one has a fallback")
        self.path = Path(path)
        self.keep = keep
        self.robot = robot
        self.cold = cold
        existed = self.path.exists() and self.path.stat().st_size > 0
        try:
            self.db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
            self.db.execute("PRAGMA journal_mode=WAL")
            self.db.execute("PRAGMA synchronous=NORMAL")
            self._migrate(existed)
        except sqlite3.DatabaseError as exc:
            raise StoreError(f"{self.path} is not a usable map store: {exc}") from exc
        self.logs: dict[str, LogState] = {}
        self.session = 0
        self.skipped: list[tuple[str, str]] = []
        self.bytes_written = 0
        self._reader = sqlite3.connect(self.path, check_same_thread=False)  # cold rows, from any thread
        self._read_lock = threading.Lock()
        self._excluded: set[int] = set()  # checkpoints that read back but could not be restored
        self._replaced: set[tuple[str, int]] = set()  # (log, generation) replaced, deleted once unused

    # ------------------------------------------------------------ schema

    def _meta(self, key: str) -> str | None:
        row = self.db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return None if row is None else str(row[0])

    def _migrate(self, existed: bool) -> None:
        """Create the schema, or bring an older store up to ``SCHEMA_VERSION``; refuse a newer or foreign one."""
        has_meta = self.db.execute("SELECT 1 FROM sqlite_master WHERE type='table' AND name='meta'").fetchone()
        version = int(self._meta("schema_version") or 0) if has_meta else 0
        if existed and not has_meta:
            raise StoreError(f"{self.path} is not an objslam map store (no meta table)")
        if version > SCHEMA_VERSION:
            raise StoreError(
                f"{self.path} has schema version {version}, newer than this release's {SCHEMA_VERSION}: "
                "upgrade objslam, or give this run another --state-dir"
            )
        robot = self._meta("robot") if has_meta else None
        if robot is not None and robot != self.robot:
            raise StoreError(
                f"{self.path} holds the map of robot {robot!r}, not {self.robot!r}: give each robot its own --state-dir"
            )
        with self.transaction():
            while 0 < version < SCHEMA_VERSION:
                MIGRATIONS[version](self.db)
                version += 1
                log.info("map store %s migrated to schema version %d", self.path, version)
            if version == 0:
                for statement in filter(str.strip, SCHEMA.split(";")):
                    self.db.execute(statement)
            self.db.execute("INSERT OR REPLACE INTO meta VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),))
            self.db.execute("INSERT OR IGNORE INTO meta VALUES ('robot', ?)", (self.robot,))
            self.db.execute("INSERT OR IGNORE INTO meta VALUES ('created', ?)", (str(time.time()),))

    def transaction(self) -> _Transaction:
        return _Transaction(self.db)

    def start_session(self, info: dict[str, Any]) -> int:
        """A new session of this map (one per start of the service); its id."""
        with self.transaction():
            cur = self.db.execute(
                "INSERT INTO sessions (started, robot, info) VALUES (?, ?, ?)",
                (time.time(), self.robot, json.dumps(info)),
            )
        self.session = int(cur.lastrowid or 0)
        return self.session

    # ------------------------------------------------------------ writing

    def checkpoint(self, small: dict[str, Any], logs: dict[str, Any], keyframes: int, frames: int) -> int:
        """Write the rows of ``logs`` new since the last checkpoint and ``small``, in one transaction; its id.

        ``logs`` are the live containers (``slam.parts``): only their new rows are encoded, so the work is the
        new rows', not the map's. Raises OSError / sqlite3.Error when the disk refuses (nothing is written).
        ``stage`` and ``write`` in one call."""
        return self.write(self.stage(small, logs, keyframes, frames))

    def stage(self, small: dict[str, Any], logs: dict[str, Any], keyframes: int, frames: int) -> Staged:
        """A checkpoint encoded: the new rows of the live ``logs`` and ``small`` as bytes, to be written by
        ``write`` (on any thread: nothing it holds is live). Call it where the logs do not change meanwhile;
        stage the next one only after the last one's ``write`` returned or raised."""
        before = dict(self.logs)  # the states themselves: ``_stage_log`` changes a copy of the ones it writes to
        staged = Staged(keyframes, frames, before)
        try:
            lengths = {name: self._stage_log(staged, name, rows) for name, rows in logs.items()}
            staged.lengths = json.dumps(lengths)
            staged.small = b"".join(encode(small))
        except BaseException:
            self.logs = before
            raise
        for name in self.cold & logs.keys():  # once committed, the store holds them and RAM need not
            rows = logs[name]
            if isinstance(rows, ColdLog):
                staged.spills.append((rows, lengths[name][1], self.loader(name, self.logs[name].generation)))
        return staged

    def write(self, staged: Staged) -> int:
        """Write a staged checkpoint in one transaction (checksums, rows, the checkpoint row, pruning); its id.
        On failure the writer's books are as before ``stage``: the next checkpoint writes these rows again."""
        t0 = time.perf_counter()
        try:
            with self.transaction():
                for at, (sql, params) in enumerate(staged.ops):
                    if isinstance(params[-1], FrozenRows):  # encoded here, on the writer thread
                        params = (*params[:-1], params[-1].encoded())
                        staged.ops[at] = (sql, params)
                    if isinstance(params[-1], bytes):
                        params = (*params, hashlib.sha256(params[-1]).digest())
                    self.db.execute(sql, params)
                cur = self.db.execute(
                    "INSERT INTO checkpoints (session, created, keyframes, frames, logs, small, sha) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?)",
                    (
                        self.session,
                        time.time(),
                        staged.keyframes,
                        staged.frames,
                        staged.lengths,
                        staged.small,
                        hashlib.sha256(staged.small).digest(),
                    ),
                )
                self._prune()
        except BaseException:
            self.logs = staged.before  # the rolled-back rows are written again next time
            raise
        self.bytes_written += staged.nbytes
        for rows, n, loader in staged.spills:
            rows.spill(n, loader)
        log.debug("checkpoint: %d keyframes written in %.1f ms", staged.keyframes, (time.perf_counter() - t0) * 1e3)
        return int(cur.lastrowid or 0)

    def _stage_log(self, staged: Staged, name: str, rows: Any) -> tuple[int, int, str]:
        state = self.logs.get(name)
        n, kind = len(rows), kind_of(rows)
        held = owner(rows)
        replaced = state is not None and state.owner is not None and state.owner is not held
        if state is None or state.chunks is None or replaced or n < state.written:
            if state is not None:  # a new container (or the log of an older checkpoint): written whole
                self._replaced.add((name, state.generation))
            generation = 0 if state is None else self._next_generation(name, state.generation)
            state = self.logs[name] = LogState(generation, 0, kind)
        elif n > state.written or state.owner is not held:
            state = self.logs[name] = replace(state, chunks=None if state.chunks is None else list(state.chunks))
        state.owner = held
        if n > state.written:
            if name in self.cold:
                for i, row in enumerate(tail(rows, state.written, n), state.written):
                    staged.add(COLD_ROW, (name, state.generation, i, b"".join(encode(row))))
            else:
                self._stage_chunk(staged, name, state, rows, state.written, n, 0)
                self._merge(staged, name, state, rows)
            state.written = n
        return state.generation, n, kind

    def _next_generation(self, name: str, generation: int) -> int:
        """A generation of ``name`` above every stored one (an older checkpoint's may have been continued)."""
        table = "cold" if name in self.cold else "chunks"
        row = self.db.execute(f"SELECT MAX(generation) FROM {table} WHERE log = ?", (name,)).fetchone()
        return max(generation, -1 if row[0] is None else int(row[0])) + 1

    def _stage_chunk(
        self, staged: Staged, name: str, state: LogState, rows: Any, first: int, stop: int, level: int
    ) -> None:
        part = tail(rows, first, stop)
        data = FrozenRows(part) if FrozenRows.admits(part) else b"".join(encode(part))
        staged.add(CHUNK, (name, state.generation, first, stop - first, level, data))
        assert state.chunks is not None
        state.chunks.append((first, stop - first, level))

    def _merge(self, staged: Staged, name: str, state: LogState, rows: Any) -> None:
        """Merge the last ``FANOUT`` chunks when they are of one level below ``TOP_LEVEL`` (repeatedly: a merge
        can complete one)."""
        chunks = state.chunks
        assert chunks is not None  # a writer's own log (``_stage_log`` starts a new generation otherwise)
        while len(chunks) >= FANOUT and len(lv := {c[2] for c in chunks[-FANOUT:]}) == 1 and min(lv) < TOP_LEVEL:
            merged = chunks[-FANOUT:]
            del chunks[-FANOUT:]
            first, stop = merged[0][0], merged[-1][0] + merged[-1][1]
            staged.add(DELETE_CHUNKS, (name, state.generation, first, stop))
            self._stage_chunk(staged, name, state, rows, first, stop, merged[0][2] + 1)

    def _prune(self) -> None:
        """Keep the newest ``keep`` checkpoints; drop the replaced log generations none of them uses."""
        ids = [r[0] for r in self.db.execute("SELECT id FROM checkpoints ORDER BY id DESC").fetchall()]
        if len(ids) <= self.keep:
            return
        self.db.execute("DELETE FROM checkpoints WHERE id <= ?", (ids[self.keep],))
        if not self._replaced:
            return
        used = {(name, s.generation) for name, s in self.logs.items()}
        for (text,) in self.db.execute("SELECT logs FROM checkpoints").fetchall():
            used.update((name, g) for name, (g, _n, _k) in json.loads(text).items())
        for name, generation in sorted(self._replaced - used):
            table = "cold" if name in self.cold else "chunks"
            self.db.execute(f"DELETE FROM {table} WHERE log = ? AND generation = ?", (name, generation))
        self._replaced &= used

    # ------------------------------------------------------------ reading

    def checkpoints(self) -> list[tuple[int, int, float, int, int]]:
        """(id, session, created, keyframes, frames) of the stored checkpoints, newest first."""
        rows = self.db.execute("SELECT id, session, created, keyframes, frames FROM checkpoints ORDER BY id DESC")
        return [tuple(r) for r in rows.fetchall()]

    def load(self) -> Loaded | None:
        """The newest checkpoint that reads back whole, its logs' rows verified; None when there is none.
        Each newer one that fails is logged and listed in ``skipped`` with its reason."""
        try:
            ids = [r[0] for r in self.checkpoints()]
        except sqlite3.DatabaseError as exc:
            raise StoreError(f"{self.path}: cannot list checkpoints: {exc}") from exc
        for checkpoint in ids:
            if checkpoint in self._excluded:
                continue
            try:
                return self._load(checkpoint)
            except (StoreError, sqlite3.DatabaseError) as exc:
                log.error("map store checkpoint %d is unusable (%s); trying the one before", checkpoint, exc)
                self.skipped.append((f"checkpoint-{checkpoint}", str(exc)))
        return None

    def _load(self, checkpoint: int) -> Loaded:
        row = self.db.execute(
            "SELECT session, created, keyframes, frames, logs, small, sha FROM checkpoints WHERE id = ?", (checkpoint,)
        ).fetchone()
        session, created, keyframes, frames, text, data, sha = row
        small = unblob(data, sha, f"checkpoint {checkpoint}")
        logs, states = {}, {}
        for name, (generation, length, kind) in json.loads(text).items():
            if name in self.cold:  # read on demand
                logs[name] = ColdLog(length=length, loader=self.loader(name, generation))
                states[name] = LogState(generation, length, kind)
            else:
                logs[name], chunks = self._read_chunks(name, generation, length, kind)
                states[name] = LogState(generation, length, kind, chunks)
        self.logs = states
        return Loaded(checkpoint, session, created, keyframes, frames, small, logs)

    def _read_chunks(
        self, name: str, generation: int, length: int, kind: str
    ) -> tuple[Any, list[tuple[int, int, int]] | None]:
        rows = self.db.execute(
            "SELECT first, count, level, data, sha FROM chunks WHERE log = ? AND generation = ? AND first < ? "
            "ORDER BY first",
            (name, generation, max(length, 1)),
        ).fetchall()
        pieces, chunks, at = [], [], 0
        for first, count, level, data, sha in rows:
            if first != at:
                raise StoreError(f"log {name}: rows {at}-{first} missing")
            pieces.append(unblob(data, sha, f"log {name} rows {first}+{count}"))
            chunks.append((first, count, level))
            at = first + count
        if at < length:
            raise StoreError(f"log {name}: {length} rows expected, {at} stored")
        # rows of a later checkpoint (this older one was loaded): the writer goes on in a new generation
        return join(kind, pieces, length), (chunks if at == length else None)

    def loader(self, name: str, generation: int) -> Callable[[int], Any]:
        """Reads row ``i`` of a cold log (on its own connection: safe from any thread, beside a checkpoint)."""

        def load(i: int) -> Any:
            with self._read_lock:
                return next(self.cold_rows(name, generation, i, i + 1, self._reader))

        return load

    def cold_rows(
        self, name: str, generation: int, start: int, stop: int, db: sqlite3.Connection | None = None
    ) -> Iterator[Any]:
        """Rows ``[start, stop)`` of a cold log, verified."""
        rows = (db or self.db).execute(
            "SELECT idx, data, sha FROM cold WHERE log = ? AND generation = ? AND idx >= ? AND idx < ? ORDER BY idx",
            (name, generation, start, stop),
        )
        at = start
        for idx, data, sha in rows:
            if idx != at:
                raise StoreError(f"log {name}: row {at} missing")
            yield unblob(data, sha, f"log {name} row {idx}")
            at += 1
        if at < stop:
            raise StoreError(f"log {name}: {stop} rows expected, {at} stored")

    def forget(self, checkpoint: int) -> None:
        """Pass over ``checkpoint`` in ``load`` from now on (it read back but could not be restored)."""
        self._excluded.add(checkpoint)

    def close(self) -> None:
        self._reader.close()
        self.db.close()


class _Transaction:
    """``with store.transaction():`` BEGIN IMMEDIATE ... COMMIT, or ROLLBACK on an exception."""

    def __init__(self, db: sqlite3.Connection):
        self.db = db

    def __enter__(self) -> None:
        self.db.execute("BEGIN IMMEDIATE")

    def __exit__(self, exc_type: Any, *_: Any) -> None:
        self.db.execute("ROLLBACK" if exc_type is not None else "COMMIT")
