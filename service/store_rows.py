"""The rows of a map store's logs (``service.map_store``): how a log's rows are sliced, joined and told apart,
and the checksummed blob each chunk, cold row and checkpoint is stored as."""

from __future__ import annotations

import hashlib
from itertools import chain, islice
from typing import Any

import numpy as np

from service.persistence import SnapshotError, decode, encode


class StoreError(Exception):
    """The map store cannot be opened or read: corrupt, truncated, of a newer schema or another robot's."""


def blob(value: Any) -> tuple[bytes, bytes]:
    data = b"".join(encode(value))
    return data, hashlib.sha256(data).digest()


def unblob(data: bytes, sha: bytes, what: str) -> Any:
    if hashlib.sha256(data).digest() != sha:
        raise StoreError(f"{what}: checksum mismatch")
    try:
        return decode(bytearray(data))
    except SnapshotError as exc:
        raise StoreError(f"{what}: {exc}") from exc


def kind_of(rows: Any) -> str:
    """How a log's rows are held: ``array``, ``dict`` (rows are its items) or ``list``."""
    return "array" if isinstance(rows, np.ndarray) else "dict" if isinstance(rows, dict) else "list"


def tail(rows: Any, start: int, stop: int | None = None) -> Any:
    """Rows ``[start, stop)`` of a log: an array slice, a list slice, or a dict's items as a list."""
    if isinstance(rows, dict):
        return list(islice(rows.items(), start, stop))
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
