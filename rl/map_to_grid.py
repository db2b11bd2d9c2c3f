"""From a SLAM map to a loop-closure grid world (dissertation Sec. 3.8, SPEC 6.9, issue 6).

1. Ground plane: ``up`` is gravity when the data has it, else the mean "up" of the upright cameras
   (the negated image y axis); the floor height is a low percentile of the points along ``up``.
2. Grid: cells of ``cell_m`` on the plane, spanning the trajectory with a margin. Free space is where
   the camera went, widened by ``free_radius`` cells; a cell is a wall when it holds at least
   ``min_points`` map points within the height band above the floor, or lies outside that free space.
   Cells the camera passed through are always free.
3. Feature blocks: one per object cluster, on the free cell nearest to the object's footprint.
4. Loop-closure locations: cells the trajectory visits in separate passes at least ``min_gap_s`` apart,
   most revisited first, at most ``max_loops``, no two within ``loop_spacing`` cells.

``GroundFrame`` maps poses to (cell, heading) for the policy in the service, and is stored in the map's
``meta["frame"]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rl.gridmap import GridMap, MapError


@dataclass(frozen=True)
class GroundFrame:
    """A grid on the ground plane: world point -> (row, col); camera rotation -> heading 0..3."""

    origin: np.ndarray  # world point at the corner of cell (0, 0), on the floor
    row_axis: np.ndarray  # unit world vector along increasing rows
    col_axis: np.ndarray  # unit world vector along increasing columns
    up: np.ndarray
    cell_m: float
    shape: tuple[int, int]

    def cells(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> (N, 2) integer (row, col), possibly outside the grid."""
        d = np.asarray(points, float) - self.origin
        return np.floor(np.stack([d @ self.row_axis, d @ self.col_axis], axis=-1) / self.cell_m).astype(int)

    def inside(self, cells: np.ndarray) -> np.ndarray:
        return (cells[:, 0] >= 0) & (cells[:, 0] < self.shape[0]) & (cells[:, 1] >= 0) & (cells[:, 1] < self.shape[1])

    def heading(self, rotation: np.ndarray) -> int:
        """The grid heading (0 up = -row, 1 right = +col, 2 down = +row, 3 left = -col) nearest the view direction."""
        forward = rotation[:, 2]
        r, c = forward @ self.row_axis, forward @ self.col_axis
        if abs(r) >= abs(c):
            return 2 if r > 0 else 0
        return 1 if c > 0 else 3

    def to_json(self) -> dict:
        return {
            "origin": self.origin.tolist(),
            "row_axis": self.row_axis.tolist(),
            "col_axis": self.col_axis.tolist(),
            "up": self.up.tolist(),
            "cell_m": self.cell_m,
            "shape": list(self.shape),
        }

    @classmethod
    def from_json(cls, doc: dict) -> GroundFrame:
        origin, row_axis, col_axis, up = (np.array(doc[k], float) for k in ("origin", "row_axis", "col_axis", "up"))
        rows, cols = doc["shape"]
        return cls(origin, row_axis, col_axis, up, float(doc["cell_m"]), (int(rows), int(cols)))


def camera_up(poses: np.ndarray) -> np.ndarray:
    """Mean up direction of upright cameras (OpenCV frame: image y points down)."""
    up = -poses[:, :3, 1].mean(axis=0)
    norm = np.linalg.norm(up)
    if norm < 0.3:
        raise MapError("cameras are not upright enough to tell which way is up; give the gravity direction")
    return up / norm


def ground_frame(
    poses: np.ndarray, points: np.ndarray, cell_m: float, up: np.ndarray | None = None, margin_cells: int = 2
) -> GroundFrame:
    """The grid frame spanning the camera positions (SPEC 6.9 ground plane); ValueError without any."""
    if len(poses) == 0:
        raise ValueError("no camera pose: an empty map has no ground frame")
    up = camera_up(poses) if up is None else np.asarray(up, float) / np.linalg.norm(up)
    seed = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    row_axis = np.cross(up, seed)
    row_axis /= np.linalg.norm(row_axis)
    col_axis = np.cross(up, row_axis)  # (row, col, up) is right-handed with col = up x row
    heights = (points if len(points) else poses[:, :3, 3]) @ up
    floor = float(np.percentile(heights, 2))
    cams = poses[:, :3, 3]
    rc = np.stack([cams @ row_axis, cams @ col_axis], axis=-1)
    lo = rc.min(axis=0) - margin_cells * cell_m
    hi = rc.max(axis=0) + margin_cells * cell_m
    rows, cols = np.ceil((hi - lo) / cell_m)
    origin = lo[0] * row_axis + lo[1] * col_axis + floor * up
    return GroundFrame(origin, row_axis, col_axis, up, cell_m, (int(rows), int(cols)))


def crossing_cells(cells: np.ndarray, timestamps: np.ndarray, min_gap_s: float) -> dict[tuple[int, int], int]:
    """Cells visited in more than one pass, with their number of passes (a pass starts after a >= gap absence)."""
    last: dict[tuple[int, int], float] = {}
    passes: dict[tuple[int, int], int] = {}
    for (r, c), t in zip(map(tuple, cells), timestamps, strict=True):
        key = (int(r), int(c))
        if key not in last or t - last[key] >= min_gap_s:
            passes[key] = passes.get(key, 0) + 1
        last[key] = t
    return {k: n for k, n in passes.items() if n > 1}


def build_grid(
    name: str,
    poses: np.ndarray,
    timestamps: np.ndarray,
    points: np.ndarray,
    objects: list[tuple[str, np.ndarray]],
    cell_m: float = 0.25,
    up: np.ndarray | None = None,
    band_m: tuple[float, float] = (0.15, 2.0),
    min_points: int = 20,
    free_radius: int = 1,
    min_gap_s: float = 10.0,
    max_loops: int = 20,
    loop_spacing: int = 2,
) -> GridMap:
    """The grid world of a map: walls, objects as feature blocks, loop-closure locations (module doc)."""
    frame = ground_frame(poses, points, cell_m, up)
    rows, cols = frame.shape
    track = frame.cells(poses[:, :3, 3])
    free = np.zeros(frame.shape, bool)
    for dr in range(-free_radius, free_radius + 1):
        for dc in range(-free_radius, free_radius + 1):
            shifted = track + np.array([dr, dc])  # (N, 2) cells moved by (dr, dc)
            ok = frame.inside(shifted)
            free[shifted[ok, 0], shifted[ok, 1]] = True
    walls = ~free
    if len(points):
        height = (points - frame.origin) @ frame.up
        obstacle = points[(height >= band_m[0]) & (height <= band_m[1])]
        oc = frame.cells(obstacle)
        oc = oc[frame.inside(oc)]
        counts = np.zeros(frame.shape, int)
        np.add.at(counts, (oc[:, 0], oc[:, 1]), 1)
        walls |= counts >= min_points
    walls[track[:, 0], track[:, 1]] = False  # the camera passed through
    passes = crossing_cells(track, timestamps, min_gap_s)
    loops: list[tuple[int, int]] = []
    for cell, _ in sorted(passes.items(), key=lambda kv: (-kv[1], kv[0])):
        if len(loops) >= max_loops:
            break
        if all(max(abs(cell[0] - a), abs(cell[1] - b)) >= loop_spacing for a, b in loops):
            loops.append(cell)
    if not loops:
        raise MapError("the trajectory never crosses itself: no loop-closure locations for a grid world")
    features = _feature_blocks(frame, walls, objects, set(loops))
    meta = {
        "frame": frame.to_json(),
        "objects": [label for label, _ in objects],
        "description": f"built from a map: {rows}x{cols} cells of {cell_m} m, {len(loops)} crossings",
    }
    return GridMap(name, walls, features, tuple(loops), meta)


def _feature_blocks(
    frame: GroundFrame, walls: np.ndarray, objects: list[tuple[str, np.ndarray]], reserved: set[tuple[int, int]]
) -> tuple[tuple[tuple[int, int], ...], ...]:
    """One single-cell block per object, on the free cell nearest to it that no other block took."""
    free = np.argwhere(~walls)
    taken = set(reserved)
    blocks = []
    for _, mean in objects:
        target = frame.cells(np.asarray(mean, float)[None])[0]
        order = np.argsort(np.abs(free - target).sum(axis=1), kind="stable")
        for r, c in free[order]:
            if (int(r), int(c)) not in taken:
                taken.add((int(r), int(c)))
                blocks.append(((int(r), int(c)),))
                break
    return tuple(blocks)
