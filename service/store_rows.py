"""The rows of a map store's logs (``service.map_store``): how a log's rows are sliced, joined and told apart,
how a stored blob is verified and read, and the records the store keeps of its logs, of a checkpoint read back
and of one staged for writing."""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass, field, is_dataclass
from itertools import chain, islice
from typing import Any

import numpy as np

from loops.archive import ColdLog
from service.persistence import SnapshotError, decode, encode


class StoreError(Exception):
    """The map store cannot be opened or read: corrupt, truncated, of a newer schema or another robot's."""


def unblob(data: bytes, sha: bytes, what: str) -> Any:
    if hashlib.sha256(data).digest() != sha:
        raise StoreError(f"{what}: checksum mismatch")
    try:
        rows = decode(bytearray(data))
        if isinstance(rows, Pieces):
            return [row for piece in rows.payloads for row in decode(bytearray(piece))]
        return rows
    except SnapshotError as exc:
        raise StoreError(f"{what}: {exc}") from exc


def kind_of(rows: Any) -> str:
    """How a log's rows are held: ``array``, ``dict`` (rows are its items) or ``list``."""
    return "array" if isinstance(rows, np.ndarray) else "dict" if isinstance(rows, dict) else "list"


def tail(rows: Any, start: int, stop: int | None = None) -> Any:
    """Rows ``[start, stop)`` of a log: an array slice, a list slice, or a dict's items as a list (the newest
    ones taken from the end: the cost of the rows taken, not of the rows before them)."""
    if isinstance(rows, dict):
        n = len(rows)
        stop = n if stop is None else min(stop, n)
        if start >= stop:
            return []
        if start < n - stop:
            return list(islice(rows.items(), start, stop))
        return list(islice(reversed(rows.items()), n - stop, n - start))[::-1]
    return rows[start:stop] if isinstance(rows, np.ndarray) else list(rows[start:stop])


def owner(rows: Any) -> Any:
    """The container a log's rows live in: an array view's is the array it views (growing replaces it)."""
    return rows.base if isinstance(rows, np.ndarray) and rows.base is not None else rows


def join(kind: str, pieces: list[Any], length: int) -> Any:
    """A log of ``kind`` from its chunks' rows, cut to ``length``."""
    if kind == "array":
        return np.concatenate(pieces)[:length] if pieces else np.zeros(0)
    rows = list(islice(chain.from_iterable(pieces), length))
    return dict(rows) if kind == "dict" else rows


@dataclass
class LogState:
    """What the store has of one log: its generation, rows written, kind, level-tagged chunks (first, count,
    level) of the current generation, and the container written from (held, so that no new container can
    take its place in memory and pass for it)."""

    generation: int
    written: int
    kind: str
    chunks: list[tuple[int, int, int]] | None = field(default_factory=list)  # None: go on in a new generation
    owner: Any = None


@dataclass(frozen=True)
class Loaded:
    """A checkpoint read back: its id, session, creation time, counts, small part and logs (cold ones lazy)."""

    checkpoint: int
    session: int
    created: float
    keyframes: int
    frames: int
    small: dict[str, Any]
    logs: dict[str, Any]


CHUNK = "INSERT OR REPLACE INTO chunks VALUES (?, ?, ?, ?, ?, ?, ?)"
COLD_ROW = "INSERT OR REPLACE INTO cold VALUES (?, ?, ?, ?, ?)"
DELETE_CHUNKS = "DELETE FROM chunks WHERE log = ? AND generation = ? AND first >= ? AND first < ?"


FROZEN_ROWS = 256
"""A chunk of at least this many rows of frozen dataclasses is encoded by the writer thread, not the caller."""


@dataclass(frozen=True)
class FrozenRows:
    """A chunk's rows to be encoded when written: a list of frozen dataclasses (factor records, feature vectors),
    which nothing changes once made, so encoding them later, on the writer thread, reads what the checkpoint
    took. A whole log written again (a window rebuilt, features pooled) is thousands of them: pickling them
    stalled the worker 20-60 ms on a map of 7,000 keyframes."""

    rows: list[Any]

    def encoded(self) -> bytes:
        """The chunk's blob, encoded ``PIECE_ROWS`` rows at a time: pickling holds the GIL, and all of a rewritten
        log at once (thousands of factor records) held it 30-70 ms, so the worker waited that long for the
        writer thread anyway; between pieces the worker takes its turn (``sys.setswitchinterval``)."""
        rows = self.rows
        if len(rows) <= PIECE_ROWS:
            return b"".join(encode(rows))
        pieces = [b"".join(encode(rows[i : i + PIECE_ROWS])) for i in range(0, len(rows), PIECE_ROWS)]
        return b"".join(encode(Pieces(pieces)))

    @staticmethod
    def admits(rows: Any) -> bool:
        """A list of ``FROZEN_ROWS`` or more, every row a frozen dataclass."""
        if not isinstance(rows, list) or len(rows) < FROZEN_ROWS:
            return False
        kinds = {type(r) for r in rows}
        return all(
            is_dataclass(k) and getattr(getattr(k, "__dataclass_params__", None), "frozen", False) for k in kinds
        )


PIECE_ROWS = 128
"""``FrozenRows`` are encoded this many rows at a time."""


@dataclass(frozen=True)
class Pieces:
    """A chunk's rows encoded piece by piece (``FrozenRows.encoded``); read back as one list."""

    payloads: list[bytes]


@dataclass
class Staged:
    """A checkpoint encoded by ``MapStore.stage``: its statements in order (a blob, last, gets its SHA-256 when
    written), the logs' lengths (JSON), the small part's bytes, the cold logs to spill once it is committed
    (log, rows stored, loader), and the writer's books as they were before it."""

    keyframes: int
    frames: int
    before: dict[str, LogState]
    ops: list[tuple[str, tuple[Any, ...]]] = field(default_factory=list)  # a blob: bytes, or FrozenRows
    lengths: str = "{}"
    small: bytes = b""
    spills: list[tuple[ColdLog, int, Callable[[int], Any]]] = field(default_factory=list)

    def add(self, sql: str, params: tuple[Any, ...]) -> None:
        self.ops.append((sql, params))

    @property
    def nbytes(self) -> int:
        """Bytes of blobs: the new rows' and the small part's (``FrozenRows`` once written)."""
        return len(self.small) + sum(len(p[-1]) for _, p in self.ops if isinstance(p[-1], bytes))
