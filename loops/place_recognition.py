"""Appearance-based loop-closure candidates: a compact global image descriptor and a similarity search.

The descriptor is a "tiny image": the grey image blurred, shrunk to 32 x 24, normalised to zero mean and
unit norm (cf. Milford's SeqSLAM, Torralba's tiny images). Cosine similarity against every stored
keyframe is one matrix-vector product; candidates respect a minimum time gap so that recent keyframes
(which always look alike) are never proposed.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

DESCRIPTOR_SIZE = (32, 24)
_LENGTH = DESCRIPTOR_SIZE[0] * DESCRIPTOR_SIZE[1]


def global_descriptor(rgb: np.ndarray) -> np.ndarray:
    """Zero-mean, unit-norm 32 x 24 grey thumbnail, as a float32 vector."""
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    small = cv2.resize(cv2.GaussianBlur(gray, (0, 0), 3.0), DESCRIPTOR_SIZE, interpolation=cv2.INTER_AREA)
    v = small.astype(np.float32).ravel()
    v -= v.mean()
    n = np.linalg.norm(v)
    return v / n if n > 1e-6 else v


@dataclass(frozen=True)
class Candidate:
    """A stored place proposed for a query, with its descriptor similarity."""

    index: int
    similarity: float


class PlaceIndex:
    """Descriptors of past keyframes with their timestamps; queried by cosine similarity."""

    def __init__(self, capacity: int = 20000):
        self._desc = np.zeros((capacity, DESCRIPTOR_SIZE[0] * DESCRIPTOR_SIZE[1]), np.float32)
        self._times = np.zeros(capacity)
        self._ids = np.zeros(capacity, dtype=np.int64)
        self.size = 0

    def add(self, place_id: int, timestamp: float, descriptor: np.ndarray) -> None:
        if self.size == len(self._desc):  # grow geometrically; places are never forgotten
            self._desc = np.concatenate([self._desc, np.zeros_like(self._desc)])
            self._times = np.concatenate([self._times, np.zeros_like(self._times)])
            self._ids = np.concatenate([self._ids, np.zeros_like(self._ids)])
        self._desc[self.size], self._times[self.size], self._ids[self.size] = descriptor, timestamp, place_id
        self.size += 1

    def state(self) -> dict:
        """The stored places as plain arrays."""
        return PlaceIndex.joined(self.logs())

    def logs(self) -> dict[str, np.ndarray]:
        """The stored places as append-only logs: views of the arrays (growing replaces them)."""
        n = self.size
        return {"places.descriptors": self._desc[:n], "places.timestamps": self._times[:n], "places.ids": self._ids[:n]}

    @staticmethod
    def joined(logs: dict) -> dict:
        """``state()`` of ``logs()`` (or of the logs read back)."""
        return {
            "descriptors": np.array(logs["places.descriptors"], np.float32).reshape(-1, _LENGTH),
            "timestamps": np.array(logs["places.timestamps"], float),
            "ids": np.array(logs["places.ids"], np.int64),
        }

    def restore(self, state: dict) -> None:
        n = len(state["ids"])
        capacity = max(len(self._desc), n)
        self._desc = np.zeros((capacity, self._desc.shape[1]), np.float32)
        self._times, self._ids = np.zeros(capacity), np.zeros(capacity, dtype=np.int64)
        self._desc[:n], self._times[:n], self._ids[:n] = state["descriptors"], state["timestamps"], state["ids"]
        self.size = n

    def query(
        self, descriptor: np.ndarray, timestamp: float, min_gap_s: float, top_k: int, min_similarity: float
    ) -> list[Candidate]:
        """Up to ``top_k`` places older than ``min_gap_s`` with similarity >= ``min_similarity``, best first."""
        old = np.nonzero(self._times[: self.size] <= timestamp - min_gap_s)[0]
        if len(old) == 0:
            return []
        # the product over every stored place, read where it lies: taking the old places' rows first copied all
        # of them (46 MB at 15,000 keyframes) on every query
        sims = (self._desc[: self.size] @ descriptor)[old]
        best = old[np.argsort(-sims)[:top_k]]
        return [
            Candidate(int(self._ids[i]), float(s))
            for i, s in zip(best, np.sort(-sims)[:top_k] * -1, strict=True)
            if s >= min_similarity
        ]
