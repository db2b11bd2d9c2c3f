"""Per-keyframe data that can live outside RAM: a cold log, and loop closure's keyframe archive built on one.

A map store (``service.map_store``) writes a cold log's rows as they come and then calls ``spill``: the rows
it holds leave RAM except the newest ``resident``, and are read back through its ``loader`` when asked for
(the last few read are kept). Without a store nothing is ever spilled, so an in-process run is unchanged.
Reads may come from the mapping thread while the worker appends: a row is appended before it is spilled,
and a spilled row is only ever read, so a lock around the row table is all it needs.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator
from typing import Any, Generic, TypeVar, overload

from loops.records import KeyframeEntry

T = TypeVar("T")
RESIDENT = 32  # newest rows always kept in RAM
CACHED = 32  # spilled rows read back and kept, least recently used dropped


class ColdLog(Generic[T]):
    """A list of rows (append-only) whose older rows may be held by a store instead of RAM."""

    def __init__(self, rows: Iterable[T] = (), length: int = 0, loader: Callable[[int], T] | None = None):
        self._rows: dict[int, T] = dict(enumerate(rows))  # the rows in RAM, by position
        self._n = max(length, len(self._rows))
        self._loader = loader
        self._cache: OrderedDict[int, T] = OrderedDict()
        self._lock = threading.Lock()
        self.loads = 0  # rows read back from the store

    @classmethod
    def of(cls, rows: Iterable[T] | ColdLog[T]) -> ColdLog[T]:
        """``rows`` as a cold log (itself when it is one already)."""
        return rows if isinstance(rows, ColdLog) else cls(rows)

    def __len__(self) -> int:
        return self._n

    @property
    def resident(self) -> int:
        """Rows held in RAM (not counting the read-back cache)."""
        return len(self._rows)

    def append(self, row: T) -> None:
        with self._lock:
            self._rows[self._n] = row
            self._n += 1

    @overload
    def __getitem__(self, i: int) -> T: ...

    @overload
    def __getitem__(self, i: slice) -> list[T]: ...

    def __getitem__(self, i: int | slice) -> T | list[T]:
        if isinstance(i, slice):
            return [self._row(k) for k in range(*i.indices(self._n))]
        if i < 0:
            i += self._n
        if not 0 <= i < self._n:
            raise IndexError(f"row {i} of a log of {self._n}")
        return self._row(i)

    def _row(self, i: int) -> T:
        with self._lock:
            if i in self._rows:
                return self._rows[i]
            if i in self._cache:
                self._cache.move_to_end(i)
                return self._cache[i]
            loader = self._loader
        if loader is None:
            raise IndexError(f"row {i} was spilled and no loader reads it back")
        row = loader(i)
        with self._lock:
            self.loads += 1
            self._cache[i] = row
            while len(self._cache) > CACHED:
                self._cache.popitem(last=False)
        return row

    def __iter__(self) -> Iterator[T]:
        return (self._row(i) for i in range(self._n))

    def spill(self, saved: int, loader: Callable[[int], T]) -> None:
        """The first ``saved`` rows are held by a store that ``loader`` reads: drop them from RAM, except the
        newest ``RESIDENT`` rows of the log."""
        with self._lock:
            self._loader = loader
            keep_from = min(saved, self._n - RESIDENT)
            for i in [k for k in self._rows if k < keep_from]:
                del self._rows[i]


class KeyframeArchive:
    """Loop closure's keyframes by index: index, time and frame of every one in RAM (``stubs``, a plain log)
    and their features in a ``ColdLog`` (same positions), read on demand once spilled."""

    def __init__(self, stubs: Iterable[tuple[int, float, int]] = (), features: ColdLog[Any] | None = None):
        self.stubs: list[tuple[int, float, int]] = [(int(k), float(t), int(f)) for k, t, f in stubs]
        self.features: ColdLog[Any] = features if features is not None else ColdLog()
        if len(self.features) != len(self.stubs):
            raise ValueError(f"{len(self.stubs)} keyframes but {len(self.features)} feature rows")
        self._position = {k: i for i, (k, _, _) in enumerate(self.stubs)}

    @classmethod
    def of_entries(cls, entries: Iterable[KeyframeEntry]) -> KeyframeArchive:
        entries = list(entries)
        return cls([(e.index, e.timestamp, e.frame) for e in entries], ColdLog(e.features for e in entries))

    def add(self, entry: KeyframeEntry) -> None:
        if entry.index in self._position:
            raise ValueError(f"keyframe {entry.index} is archived already")
        self._position[entry.index] = len(self.stubs)
        self.features.append(entry.features)
        self.stubs.append((entry.index, entry.timestamp, entry.frame))

    def __len__(self) -> int:
        return len(self.stubs)

    def __contains__(self, index: object) -> bool:
        return index in self._position

    def __getitem__(self, index: int) -> KeyframeEntry:
        i = self._position[index]
        k, t, f = self.stubs[i]
        return KeyframeEntry(k, t, f, self.features[i])

    def get(self, index: int) -> KeyframeEntry | None:
        return self[index] if index in self._position else None

    def timestamp(self, index: int) -> float | None:
        """The time of keyframe ``index``; None when it is not archived."""
        i = self._position.get(index)
        return None if i is None else self.stubs[i][1]

    def entries(self) -> list[KeyframeEntry]:
        """Every keyframe with its features (all read back: for a whole-state snapshot)."""
        return [self[k] for k, _, _ in self.stubs]
