"""The agent's cone of vision and its top-down observation image (dissertation Sec. 3.5.3, Fig. 3.6).

Headings are 0 up (-row), 1 right (+col), 2 down (+row), 3 left (-col). A cell is seen when the ray
from the agent's cell centre to the cell's centre lies within ``half_angle`` of the heading and passes
no wall before reaching it (walls themselves are seen). The observation is the whole grid, black
where unseen, resampled to ``size`` x ``size`` pixels by nearest neighbour.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from rl.gridmap import GridMap, feature_colours

HEADINGS = np.array([[-1, 0], [0, 1], [1, 0], [0, -1]])
UNSEEN = (0, 0, 0)
FREE = (60, 60, 60)
WALL_COLOUR = (255, 255, 255)
AGENT = (255, 0, 0)
LOOP_COLOUR = (140, 140, 140)
OBS_SIZE = 84
_RENDERERS: dict[tuple, Renderer] = {}


def visible_cells(
    walls: np.ndarray, cell: tuple[int, int], heading: int, half_angle_deg: float = 30.0, step: float = 0.25
) -> np.ndarray:
    """(rows, cols) bool mask of the cells inside the cone of vision and not occluded by walls."""
    rows, cols = walls.shape
    rr, cc = np.mgrid[0:rows, 0:cols]
    d = np.stack([rr - cell[0], cc - cell[1]], axis=-1).reshape(-1, 2).astype(float)
    dist = np.hypot(d[:, 0], d[:, 1])
    cos_to_heading = (d @ HEADINGS[heading]) / np.maximum(dist, 1e-9)
    in_cone = (dist > 0) & (cos_to_heading >= math.cos(math.radians(half_angle_deg)) - 1e-9)
    idx = np.flatnonzero(in_cone)
    seen = np.zeros(rows * cols, dtype=bool)
    seen[cell[0] * cols + cell[1]] = True  # the agent's own cell
    if idx.size:
        n = math.ceil(dist[idx].max() / step)
        s = (np.arange(1, n) / n)[None, :, None]  # fractions along each ray, endpoints excluded
        points = np.array(cell, dtype=float)[None, None, :] + s * d[idx][:, None, :]
        pr = np.clip(np.rint(points[..., 0]).astype(int), 0, rows - 1)
        pc = np.clip(np.rint(points[..., 1]).astype(int), 0, cols - 1)
        target = (pr == rr.ravel()[idx][:, None]) & (pc == cc.ravel()[idx][:, None])
        blocked = (walls[pr, pc] & ~target).any(axis=1)
        seen[idx[~blocked]] = True
    return seen.reshape(rows, cols)


def renderer_for(grid: GridMap) -> Renderer:
    """One shared renderer (and visibility cache) per map, so parallel environments warm it up once."""
    key = (grid.name, grid.walls.tobytes(), grid.features, grid.loops)
    if key not in _RENDERERS:
        _RENDERERS[key] = Renderer(grid)
    return _RENDERERS[key]


class Renderer:
    """Colours a map's cells once, then draws observations from visibility masks (cached per pose)."""

    def __init__(self, grid: GridMap, size: int = OBS_SIZE, half_angle_deg: float = 30.0, cache: int = 50_000):
        self.grid = grid
        self.half_angle_deg = half_angle_deg
        rows, cols = grid.shape
        colours = np.empty((rows, cols, 3), dtype=np.uint8)
        colours[:] = FREE
        colours[grid.walls] = WALL_COLOUR
        ids = grid.feature_ids()
        palette = feature_colours(len(grid.features))
        colours[ids > 0] = palette[ids[ids > 0] - 1]
        self.colours = colours
        self._rows_px = (np.arange(size) * rows) // size
        self._cols_px = (np.arange(size) * cols) // size
        self._masks: dict[tuple[int, int, int], np.ndarray] = {}
        self._cache = cache

    def mask(self, cell: tuple[int, int], heading: int) -> np.ndarray:
        key = (cell[0], cell[1], heading)
        m = self._masks.get(key)
        if m is None:
            m = visible_cells(self.grid.walls, cell, heading, self.half_angle_deg)
            if len(self._masks) < self._cache:
                self._masks[key] = m
        return m

    def observation(self, cell: tuple[int, int], heading: int) -> np.ndarray:
        """The (size, size, 3) uint8 image of what the agent sees, the agent's cell drawn in red."""
        image = np.where(self.mask(cell, heading)[..., None], self.colours, np.uint8(0))
        image[cell] = AGENT
        image = image[self._rows_px][:, self._cols_px]
        if len(self._rows_px) < 3 * self.grid.shape[0] or len(self._cols_px) < 3 * self.grid.shape[1]:
            # cells under 3 pixels: the agent is drawn as a 3 x 3 block centred on its cell, to stay visible
            r = int(np.searchsorted(self._rows_px, cell[0]))
            c = int(np.searchsorted(self._cols_px, cell[1]))
            image[max(r - 1, 0) : r + 2, max(c - 1, 0) : c + 2] = AGENT
        return image

    def full_view(self, cell: tuple[int, int] | None = None, heading: int = 0, px: int | None = None) -> np.ndarray:
        """A human view of the whole grid: loop-closure locations numbered and, given the agent's cell, its lit
        cone and heading."""
        rows, cols = self.grid.shape
        px = px or max(4, min(40, 840 // max(rows, cols)))
        base = self.colours.astype(np.float32)
        for r, c in self.grid.loops:
            base[r, c] = LOOP_COLOUR
        if cell is not None:
            base[~self.mask(cell, heading) & ~self.grid.walls] *= 0.45
            base[cell] = AGENT
        image = np.ascontiguousarray(np.repeat(np.repeat(base.astype(np.uint8), px, 0), px, 1))
        if cell is not None:
            centre = (int((cell[1] + 0.5) * px), int((cell[0] + 0.5) * px))
            tip = (centre[0] + int(HEADINGS[heading][1] * px * 0.45), centre[1] + int(HEADINGS[heading][0] * px * 0.45))
            cv2.arrowedLine(image, centre, tip, (255, 255, 0), max(1, px // 8), tipLength=0.5)
        if px >= 12:
            for loop, (r, c) in enumerate(self.grid.loops):
                cv2.putText(
                    image,
                    str(loop + 1),
                    (c * px + 2, r * px + px - 3),
                    cv2.FONT_HERSHEY_SIMPLEX,
                    px / 40,
                    (0, 0, 0),
                    1,
                    cv2.LINE_AA,
                )
        return image
