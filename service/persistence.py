"""Snapshots of the service state in the state directory: atomic, checksummed, the previous ones kept.

A snapshot is ``<state_dir>/snapshots/snapshot-<n>.bin`` (n increasing): a 48-byte header (magic
``OBJSLAM1``, payload length as uint64 little-endian, SHA-256 of the payload) and the payload, a pickle
(protocol 5, arrays out of band: see ``encode``) of plain data: numbers, strings, numpy arrays and
objslam's own dataclasses. It is read back with an unpickler that admits nothing else (plain names only,
each resolved object checked, no module imported on the file's word), so a snapshot cannot run code. The
SHA-256 in the header detects accidents (a torn write, a flipped bit), not tampering: the unpickler is what
makes a crafted file harmless.

Writing goes to a temporary file in the same directory, fsync, ``os.replace``, fsync of the directory;
then all but the newest ``keep`` snapshots are deleted. A crash at any point leaves the previous
snapshots intact. Loading takes the newest snapshot whose length and checksum verify and reports every
newer one it skipped, and why.
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import io
import logging
import os
import pickle
import re
import struct
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

MAGIC = b"OBJSLAM1"
HEADER = struct.Struct("<8sQ32s")
TABLE = struct.Struct("<QQ")
FORMAT = 1
_NAME = re.compile(r"^snapshot-(\d{8,})\.bin$")
_OWN_PACKAGES = ("perception.", "graph.", "service.", "slam.", "loops.", "rl.", "sources.")
MOVED = {
    "service.pipeline": "slam.records",
    "service.loop_closure": "loops.records",
    "perception.place_recognition": "loops.place_recognition",
}
"""Modules whose dataclasses snapshots of earlier releases name (release 0.1.0 -> now)."""
_ALLOWED = (
    {("builtins", n) for n in ("set", "frozenset", "complex", "slice", "bytearray")}
    | {("collections", "Counter"), ("collections", "OrderedDict"), ("numpy", "dtype"), ("numpy", "ndarray")}
    | {(m, n) for m in ("numpy.core.multiarray", "numpy._core.multiarray") for n in ("_reconstruct", "scalar")}
    | {(m, "_frombuffer") for m in ("numpy.core.numeric", "numpy._core.numeric")}
)


class SnapshotError(Exception):
    """A snapshot file is truncated, corrupt, of another format, or holds a type it must not."""


def encode(state: Any) -> list[memoryview]:
    """The payload of a snapshot of ``state`` (plain data only), as pieces to write back to back.

    Pickle protocol 5 with out-of-band buffers: a table (stream length, buffer count, buffer lengths), the
    pickle stream, then each array's memory as it is, so arrays are written without being copied. The
    pieces share memory with ``state``: write them before it changes.
    """
    buffers: list[pickle.PickleBuffer] = []
    stream = pickle.dumps({"format": FORMAT, "state": state}, protocol=5, buffer_callback=buffers.append)
    raws = [b.raw() for b in buffers]
    table = TABLE.pack(len(stream), len(raws)) + struct.pack(f"<{len(raws)}Q", *(r.nbytes for r in raws))
    return [memoryview(table), memoryview(stream), *raws]


class _PlainUnpickler(pickle.Unpickler):
    """Admits numpy arrays, a few builtins and the dataclasses of objslam's packages; nothing callable else."""

    def find_class(self, module: str, name: str) -> Any:
        module = MOVED.get(module, module)
        # Pickle protocol 4 resolves a dotted name attribute by attribute, and a walk like
        # ``numpy.dtypes`` + ``__builtins__.get`` reaches eval: only plain public names are looked up, and
        # what they resolve to is checked before it is returned.
        # Modules are never imported on the file's word: objslam's own must be loaded already.
        if (module, name) in _ALLOWED:
            return super().find_class(module, name)
        if not name.isidentifier() or name.startswith("_"):
            raise SnapshotError(f"snapshot refers to {module}.{name}, which is not plain data")
        if module == "numpy.dtypes":  # the dtype classes (numpy >= 2 pickles dtypes by them)
            cls = super().find_class(module, name)
            if isinstance(cls, type) and issubclass(cls, np.dtype):
                return cls
        elif module.startswith(_OWN_PACKAGES) and module in sys.modules:
            cls = super().find_class(module, name)
            if isinstance(cls, type) and (dataclasses.is_dataclass(cls) or issubclass(cls, enum.Enum)):
                return cls
        raise SnapshotError(f"snapshot refers to {module}.{name}, which is not plain data")


def decode(payload: bytes | bytearray | memoryview) -> dict[str, Any]:
    """The state of a snapshot payload; raises SnapshotError when it cannot be read back.

    Arrays are views of ``payload`` (writable when it is a bytearray), not copies.
    """
    view = memoryview(payload)
    try:
        n_stream, n_buffers = TABLE.unpack_from(view)
        if TABLE.size + 8 * n_buffers > len(view):
            raise SnapshotError("buffer table longer than the payload")
        sizes = struct.unpack_from(f"<{n_buffers}Q", view, TABLE.size)
    except struct.error as exc:
        raise SnapshotError(f"unreadable buffer table: {exc}") from exc
    offset = TABLE.size + 8 * n_buffers + n_stream
    stream = view[offset - n_stream : offset]
    buffers = []
    for size in sizes:
        buffers.append(view[offset : offset + size])
        offset += size
    if offset != len(view):
        raise SnapshotError("payload length does not match its buffer table")
    try:
        data = _PlainUnpickler(io.BytesIO(stream), buffers=buffers).load()
    except SnapshotError:
        raise
    except Exception as exc:  # a corrupt pickle can raise almost anything
        raise SnapshotError(f"unreadable payload: {exc!r}") from exc
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise SnapshotError(f"unknown snapshot format {data.get('format') if isinstance(data, dict) else '?'}")
    return data["state"]


def header(pieces: list[memoryview]) -> bytes:
    """A snapshot file's header: magic, payload length, SHA-256 of the payload."""
    digest, size = hashlib.sha256(), 0
    for piece in pieces:
        digest.update(piece)
        size += piece.nbytes
    return HEADER.pack(MAGIC, size, digest.digest())


def seal(pieces: list[memoryview]) -> bytes:
    """The bytes of a snapshot file: header + payload."""
    return header(pieces) + b"".join(pieces)


def unseal(data: bytes | bytearray) -> memoryview:
    """The payload of a snapshot file's bytes, after checking magic, length and checksum."""
    if len(data) < HEADER.size:
        raise SnapshotError(f"truncated: {len(data)} bytes, shorter than the header")
    magic, length, digest = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise SnapshotError("not a snapshot (bad magic)")
    payload = memoryview(data)[HEADER.size :]
    if len(payload) != length:
        raise SnapshotError(f"truncated: {len(payload)} of {length} payload bytes")
    if hashlib.sha256(payload).digest() != digest:
        raise SnapshotError("checksum mismatch")
    return payload


@dataclass(frozen=True)
class Written:
    """One snapshot written: its file, size in bytes, and seconds taken (checksum, write, fsync, rename)."""

    path: Path
    size: int
    write_s: float


class SnapshotStore:
    """Numbered snapshot files in one directory; the newest ``keep`` are kept."""

    def __init__(self, directory: Path, keep: int = 3):
        if keep < 2:
            raise ValueError("keep at least two snapshots, so a bad newest one has a fallback")
        self.directory = Path(directory)
        self.keep = keep
        self.directory.mkdir(parents=True, exist_ok=True)
        for stale in self.directory.glob(".snapshot-*.tmp"):  # a write cut short by a crash
            log.info("removing unfinished snapshot %s", stale.name)
            stale.unlink(missing_ok=True)

    def snapshots(self) -> list[Path]:
        """Snapshot files, oldest first."""
        found = [(int(m.group(1)), p) for p in self.directory.iterdir() if (m := _NAME.match(p.name))]
        return [p for _, p in sorted(found)]

    def write(self, payload: list[memoryview]) -> Written:
        """Write ``payload`` (``encode``'s pieces) as the next snapshot, atomically and durably; prune the oldest."""
        t0 = time.perf_counter()
        existing = self.snapshots()
        last = _NAME.match(existing[-1].name) if existing else None  # ``snapshots()`` lists only matching names
        number = int(last.group(1)) + 1 if last else 1
        path = self.directory / f"snapshot-{number:08d}.bin"
        fd, tmp = tempfile.mkstemp(dir=self.directory, prefix=".snapshot-", suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as fh:
                fh.write(header(payload))
                for piece in payload:
                    fh.write(piece)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        _fsync_dir(self.directory)
        for old in [*existing, path][: -self.keep]:
            old.unlink(missing_ok=True)
        return Written(path, HEADER.size + sum(p.nbytes for p in payload), time.perf_counter() - t0)

    def candidates(self, skipped: list[tuple[str, str]]) -> Iterator[tuple[Path, dict[str, Any]]]:
        """Decoded snapshots, newest first; each one that does not verify is logged and added to ``skipped``."""
        for path in reversed(self.snapshots()):
            try:
                state = decode(unseal(_read(path)))
            except (SnapshotError, OSError) as exc:
                log.error("snapshot %s is unusable (%s); trying the previous one", path.name, exc)
                skipped.append((path.name, str(exc)))
                continue
            yield path, state


def _read(path: Path) -> bytearray:
    """A file's bytes, writable (arrays decoded from a snapshot are views of them)."""
    data = bytearray(path.stat().st_size)
    with path.open("rb") as fh:
        n = fh.readinto(data)
    return data[:n] if n < len(data) else data


def _fsync_dir(directory: Path) -> None:
    """Make a rename in ``directory`` durable (no-op where directories cannot be opened, e.g. Windows)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
