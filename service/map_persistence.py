"""A service's map in its state directory: resume from the map store, checkpoint it as keyframes arrive.

The store is ``<state_dir>/map.db`` (``service.map_store``). Each checkpoint writes what is new since the
previous one, so its cost follows the new keyframes, not the map. A state directory of the snapshot release
(``<state_dir>/snapshots/``, ``service.persistence``) is migrated: its newest good snapshot is restored and the
first checkpoint writes it into the store; the snapshots are then left as they were, unused.

A store that cannot be opened (not a database, a newer schema) is moved aside as ``map.db.unusable-<time>``
with the reason logged and in ``status``, and a new map begins; one of another robot is refused.
"""

from __future__ import annotations

import logging
import sqlite3
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

from service.config import ConfigError
from service.heap import building_map, settle_map
from service.map_store import SCHEMA_VERSION, MapStore, StoreError
from service.persistence import SnapshotStore
from service.store_rows import Staged
from slam.core import MAPPING_LAG, SlamCore
from slam.parts import COLD, CoreParts, assemble

log = logging.getLogger(__name__)

FIRST_BACKOFF_S, MAX_BACKOFF_S = 1.0, 300.0
"""After a failed checkpoint the next periodic one waits this long, doubling up to the maximum."""
STORE_NAME = "map.db"


class Persistence:
    """Resume from the newest good checkpoint; checkpoint every ``every_keyframes`` keyframes.

    A checkpoint holds the state the service gives as a small part and append-only logs (``slam.parts``);
    ``status()`` reports what was written and what the service resumed from.
    """

    def __init__(self, directory: Path, robot: str, every_keyframes: int = 1, keep: int = 3):
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.robot = robot
        self.every_keyframes = every_keyframes
        self.skipped: list[tuple[str, str]] = []
        self.store = self._open(keep)
        self.written = self.failed = 0
        self.last: dict[str, Any] | None = None
        self.resumed_from: dict[str, Any] | None = None
        self._saved = (0, 0)  # (keyframes, frames processed) of the newest checkpoint
        self._backoff_s = self._retry_at = 0.0  # after a failed write: the wait before the next try, and its end
        self.last_error: str | None = None
        self._writer = ThreadPoolExecutor(1, thread_name_prefix="map-store")
        self._inflight: Future[dict[str, Any] | str] | None = None  # the checkpoint being written
        self._reap_lock = threading.Lock()

    def _open(self, keep: int) -> MapStore:
        path = self.directory / STORE_NAME
        try:
            store = MapStore(path, self.robot, COLD, keep)
        except StoreError as exc:
            if "holds the map of robot" in str(exc):
                raise ConfigError(str(exc)) from exc
            aside = path.with_name(f"{STORE_NAME}.unusable-{int(time.time())}")
            log.error("map store %s is unusable (%s): moved to %s, starting a new map", path, exc, aside.name)
            for suffix in ("", "-wal", "-shm"):
                source = path.with_name(path.name + suffix)
                if source.exists():
                    source.rename(aside.with_name(aside.name + suffix))
            self.skipped.append((STORE_NAME, str(exc)))
            store = MapStore(path, self.robot, COLD, keep)
        return store

    def resume(self, restore: Callable[[dict[str, Any]], None], join: Callable[[dict, dict], dict]) -> bool:
        """Restore the newest good checkpoint (``restore(join(small, logs))``), else migrate the newest good
        snapshot of an older release; start this run's session. True when something was resumed."""
        with building_map():
            resumed = self._resume_store(restore, join) or self._migrate(restore)
        self.store.start_session({"resumed": self.resumed_from})
        return resumed

    def _resume_store(self, restore: Callable[[dict[str, Any]], None], join: Callable[[dict, dict], dict]) -> bool:
        while True:
            try:
                loaded = self.store.load()
            except StoreError as exc:
                self.skipped.append((STORE_NAME, str(exc)))
                return False
            self.skipped.extend(s for s in self.store.skipped if s not in self.skipped)
            if loaded is None:
                return False
            try:
                restore(join(loaded.small, loaded.logs))
            except Exception as exc:  # e.g. a state of an incompatible version: the one before, never crash
                log.exception("checkpoint %d cannot be restored; trying the one before", loaded.checkpoint)
                self.skipped.append((f"checkpoint-{loaded.checkpoint}", f"cannot be restored: {exc!r}"))
                self.store.forget(loaded.checkpoint)
                continue
            source = f"{STORE_NAME}#checkpoint-{loaded.checkpoint}"
            self._resumed(source, loaded.keyframes, loaded.frames, loaded.created)
            return True

    def _migrate(self, restore: Callable[[dict[str, Any]], None]) -> bool:
        """Restore the newest good snapshot of a release before the map store (``snapshots/``)."""
        directory = self.directory / "snapshots"
        if not directory.is_dir():
            return False
        for path, snap in SnapshotStore(directory).candidates(self.skipped):
            if snap.get("robot", self.robot) != self.robot:
                raise ConfigError(
                    f"state dir {self.directory} holds the map of robot {snap['robot']!r}, "
                    f"not {self.robot!r}: give each robot its own --state-dir"
                )
            try:
                restore(snap["state"])
            except Exception as exc:
                log.exception("snapshot %s cannot be restored; trying the previous one", path.name)
                self.skipped.append((path.name, f"cannot be restored: {exc!r}"))
                continue
            self._resumed(path.name, snap["keyframes"], snap["frames_processed"], snap["created"])
            self._saved = (0, 0)  # the first checkpoint writes it all into the store
            log.info("migrating %s into the map store %s", path, STORE_NAME)
            return True
        return False

    def _resumed(self, source: str, keyframes: int, frames: int, created: float) -> None:
        self._saved = (keyframes, frames)
        self.resumed_from = {"file": source, "keyframes": keyframes, "frames_processed": frames, "created": created}
        log.info("resumed from %s: %d keyframes, %d frames processed", source, keyframes, frames)

    def due(self, keyframes: int, idle: bool = True, lag: int = MAPPING_LAG) -> bool:
        """True once ``every_keyframes`` keyframes were added since the newest checkpoint and the keyframe
        mapping is ``idle`` (taking the state waits for its running stages: a checkpoint waits a few frames for
        them rather than the worker for it), or ``lag`` more keyframes were added meanwhile (``MAPPING_LAG``;
        live, ``LIVE_MAX_PENDING``: tracking never waits for the mapping below that either); and no
        failed write is waiting out its backoff (a full or read-only disk is not retried after every frame)."""
        self._reap()
        if self.writing:  # one checkpoint at a time: the next one takes the rows new since this one
            return False
        behind = keyframes - self._saved[0]
        ready = behind >= self.every_keyframes and (idle or behind >= self.every_keyframes + lag)
        return ready and time.monotonic() >= self._retry_at

    def changed(self, keyframes: int, frames: int) -> bool:
        """True when there is work that the newest checkpoint does not hold (one being written counts once
        committed)."""
        self.settle()
        return (keyframes, frames) != self._saved

    def save(
        self,
        small: dict[str, Any],
        logs: dict[str, Any],
        keyframes: int,
        frames: int,
        capture_s: float = 0.0,
        wait: bool = False,
    ) -> bool:
        """Checkpoint ``small`` and the new rows of ``logs`` (live: call before they change). The rows are encoded
        here; checksums, SQLite and the commit run on the writer thread, so the caller waits only for the
        encoding. A checkpoint still being written is waited for first. ``wait``: also for this one, and its
        outcome returned. A failed write is logged and counted (the service keeps mapping, the rows are written
        with the next checkpoint)."""
        self.settle()
        t0 = time.perf_counter()
        staged = self.store.stage(small, logs, keyframes, frames)
        settle_map()  # the map lives on: full collections need not scan it again (``service.heap``)
        encode_s = time.perf_counter() - t0
        self._inflight = self._writer.submit(self._write, staged, capture_s, encode_s)
        return self.settle() if wait else True

    def _write(self, staged: Staged, capture_s: float, encode_s: float) -> dict[str, Any] | str:
        """On the writer thread: the checkpoint's record, or why it failed."""
        t0 = time.perf_counter()
        try:
            checkpoint = self.store.write(staged)
        except (OSError, sqlite3.Error) as exc:
            return str(exc)
        return {
            "file": f"{STORE_NAME}#checkpoint-{checkpoint}",
            "keyframes": staged.keyframes,
            "frames_processed": staged.frames,
            "bytes": staged.nbytes,
            "capture_ms": round(capture_s * 1e3, 3),
            "encode_ms": round(encode_s * 1e3, 3),
            "write_ms": round((time.perf_counter() - t0) * 1e3, 3),
        }

    @property
    def writing(self) -> bool:
        """A checkpoint is being written (on the writer thread)."""
        return self._inflight is not None and not self._inflight.done()

    def settle(self) -> bool:
        """Wait for the checkpoint being written, if any, and take its outcome: True when it was committed (or
        there was none)."""
        with self._reap_lock:
            future, self._inflight = self._inflight, None
            if future is None:
                return True
            outcome = future.result()
            if isinstance(outcome, str):
                self.failed += 1
                self._backoff_s = min(MAX_BACKOFF_S, self._backoff_s * 2 if self._backoff_s else FIRST_BACKOFF_S)
                self._retry_at = time.monotonic() + self._backoff_s
                self.last_error = outcome
                log.error("could not checkpoint %s: %s; next try in %.0f s", self.store.path, outcome, self._backoff_s)
                return False
            self._backoff_s, self._retry_at, self.last_error = 0.0, 0.0, None
            self.written += 1
            self._saved = (outcome["keyframes"], outcome["frames_processed"])
            self.last = outcome
            return True

    def _reap(self) -> None:
        """Take the outcome of a checkpoint written meanwhile (never waits)."""
        if self._inflight is not None and self._inflight.done():
            self.settle()

    def status(self, core: SlamCore | None = None) -> dict[str, Any]:
        """The ``persistence`` object of the status reply (docs/protocol.md), with ``core``'s session."""
        self._reap()
        return {
            "state_dir": str(self.directory),
            "every_keyframes": self.every_keyframes,
            "snapshots_written": self.written,
            "failed_writes": self.failed,
            "last_error": self.last_error,
            "retry_in_s": round(max(0.0, self._retry_at - time.monotonic()), 1) if self.last_error else None,
            "last_snapshot": self.last,
            "resumed_from": self.resumed_from,
            "skipped_snapshots": [{"file": f, "reason": r} for f, r in self.skipped],
            "store": {
                "path": str(self.store.path),
                "schema_version": SCHEMA_VERSION,
                "session": self.store.session,
                "bytes": _size(self.store.path),
            },
            "session": None if core is None else self._session(core),
        }

    def _session(self, core: SlamCore) -> dict[str, Any]:
        """This run's session: whether it began anywhere (``first_keyframe``: its first keyframe) and, if so,
        whether its newest keyframe is localized in the stored map (joined to keyframe 0's segment) and the
        stored keyframe it matched last."""
        first, newest = core.session_keyframe, core.graph.num_keyframes - 1
        localized = first is None or (newest >= first and core.segments.tied(newest))
        return {
            "id": self.store.session,
            "first_keyframe": first,
            "localized": bool(localized),
            "against_keyframe": core.segments.last_match if first is not None and localized else None,
        }

    def close(self) -> None:
        self.settle()
        self._writer.shutdown()
        self.store.close()


def _size(path: Path) -> int:
    """Bytes of a SQLite database with its write-ahead log."""
    return sum(p.stat().st_size for p in (path, path.with_name(path.name + "-wal")) if p.exists())


def service_state(small: dict[str, Any], logs: dict[str, Any]) -> dict[str, Any]:
    """A checkpoint's parts as the state ``ServiceNode._restore`` reads: the core's (``small["pipeline"]`` and
    the logs) in ``slam.snapshot.core_state``'s format, the service's counters as they are."""
    return {**small, "pipeline": assemble(CoreParts(small["pipeline"], logs), materialize=False)}
