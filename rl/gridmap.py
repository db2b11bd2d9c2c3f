"""Grid-world maps for loop-closure training (dissertation Sec. 3.5.1, Fig. 3.5; SPEC 6.9).

A map is a JSON file a person can edit::

    {"name": "config1", "rows": ["##########", "#........#", ...],
     "features": [[[1, 1], [1, 2]], [[3, 8]]],      # each feature block: its cells [row, col]
     "loops": [[2, 2], [2, 7]]}                      # loop-closure locations [row, col]

``rows`` draws the layout: ``#`` is a wall or obstacle, any other character free space. Feature
blocks lie on free cells (the agent may move through them) and each is drawn in its own colour.
"""

from __future__ import annotations

import colorsys
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

WALL = "#"
MAPS_DIR = Path(__file__).resolve().parent / "maps"


class MapError(ValueError):
    """A map file is malformed or inconsistent."""


@dataclass(frozen=True)
class GridMap:
    """Walls, distinct feature blocks and loop-closure locations of an N x M grid."""

    name: str
    walls: np.ndarray  # (rows, cols) bool
    features: tuple[tuple[tuple[int, int], ...], ...]
    loops: tuple[tuple[int, int], ...]
    meta: dict = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        rows, cols = self.shape
        for r, c in self.loops + tuple(cell for block in self.features for cell in block):
            if not (0 <= r < rows and 0 <= c < cols):
                raise MapError(f"{self.name}: cell {(r, c)} lies outside the {rows}x{cols} grid")
            if self.walls[r, c]:
                raise MapError(f"{self.name}: cell {(r, c)} is a wall")
        if len(set(self.loops)) != len(self.loops):
            raise MapError(f"{self.name}: duplicate loop-closure locations")
        if not self.loops:
            raise MapError(f"{self.name}: a map needs at least one loop-closure location")
        if (~self.walls).sum() < 2:
            raise MapError(f"{self.name}: fewer than two free cells")

    @property
    def shape(self) -> tuple[int, int]:
        return self.walls.shape

    @property
    def n_loops(self) -> int:
        return len(self.loops)

    def feature_ids(self) -> np.ndarray:
        """(rows, cols) int array: 0 for no feature, k + 1 for cells of feature block k."""
        ids = np.zeros(self.shape, dtype=np.int32)
        for k, block in enumerate(self.features):
            for r, c in block:
                ids[r, c] = k + 1
        return ids

    def loop_index(self) -> np.ndarray:
        """(rows, cols) int array: 0 off loop-closure locations, l + 1 on location l (the action)."""
        index = np.zeros(self.shape, dtype=np.int32)
        for loop, (r, c) in enumerate(self.loops):
            index[r, c] = loop + 1
        return index

    def to_json(self) -> dict:
        rows = ["".join(WALL if w else "." for w in row) for row in self.walls]
        return {
            "name": self.name,
            "rows": rows,
            "features": [[list(cell) for cell in block] for block in self.features],
            "loops": [list(cell) for cell in self.loops],
            **({"meta": self.meta} if self.meta else {}),
        }

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        doc = self.to_json()
        # one map row, feature block or location per line keeps the file readable and diffable
        lines = [f'{{"name": {json.dumps(doc["name"])},']
        if "meta" in doc:
            lines.append(f' "meta": {json.dumps(doc["meta"])},')
        for key in ("rows", "features", "loops"):
            items = ",\n  ".join(json.dumps(v) for v in doc[key])
            lines.append(f' "{key}": [\n  {items}\n ]' + ("," if key != "loops" else ""))
        path.write_text("\n".join(lines) + "\n}\n")
        return path

    @classmethod
    def from_json(cls, doc: dict) -> GridMap:
        try:
            rows = doc["rows"]
            width = len(rows[0])
            if any(len(r) != width for r in rows):
                raise MapError("rows differ in length")
            walls = np.array([[ch == WALL for ch in r] for r in rows], dtype=bool)
            features = tuple(tuple((int(r), int(c)) for r, c in block) for block in doc.get("features", []))
            loops = tuple((int(r), int(c)) for r, c in doc["loops"])
        except (KeyError, IndexError, TypeError, ValueError) as exc:
            raise MapError(f"malformed map: {exc}") from exc
        return cls(str(doc.get("name", "map")), walls, features, loops, dict(doc.get("meta", {})))

    @classmethod
    def load(cls, path: str | Path) -> GridMap:
        """A map file, or the name of a shipped configuration (``config1`` ... ``config6``)."""
        path = Path(path)
        if not path.suffix and not path.exists():
            path = MAPS_DIR / f"{path.name}.json"
        try:
            doc = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise MapError(f"cannot read map {path}: {exc}") from exc
        return cls.from_json(doc)


def feature_colours(n: int) -> np.ndarray:
    """(n, 3) uint8 distinct, saturated colours (golden-ratio hues), none white, grey or black."""
    hues = (0.13 + np.arange(n) * 0.618033988749895) % 1.0  # pure red is the agent's
    values = 0.65 + 0.35 * ((np.arange(n) // 7) % 2)
    return np.array(
        [[round(255 * x) for x in colorsys.hsv_to_rgb(h, 0.85, v)] for h, v in zip(hues, values, strict=True)],
        dtype=np.uint8,
    ).reshape(n, 3)


SHIPPED = ("config1", "config2", "config3", "config4", "config5", "config6")
