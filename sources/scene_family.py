"""The synthetic scene family (``synthetic:family``): a randomized room, its furniture and a camera path per seed.

Every seed gives a room of 4-9 x 4-9 m (2.5-3 m high), textured like ``synthetic:room`` or, in about 30 % of
the scenes, with texture-poor (plain painted) walls; a camera path of kind ``PATH_KINDS[seed % 4]`` (inward
laps, outward laps, a walk through the room, a handheld sweep; ``sources.family_paths``: yaw rate <= 60 deg/s);
and objects rejection-sampled at least ``CLEARANCE_M`` from the path, on the walls' side of it or in the middle:

- along the walls: couches, refrigerators, beds (rooms over 6 m), desks with clutter, rows of chairs, tvs and
  clocks on the wall, plants, suitcases; free-standing: dining tables with rows of chairs along their sides,
  rows of chairs, plants, suitcases, couches (more of them for inward laps, which see little else within
  the depth range: the far walls of a large room are 4-7 m away); teddy bears and books on couches and beds;
  nothing where the path never looks (inside outward laps, behind a sweep);
- rows of 2-5 same-class objects (``ROW_LABELS``: chairs on the floor, cups, bottles and books on tables) whose
  centre-to-centre spacing is one of ``SPACING_BUCKETS_M`` +- 2 cm (0.3-1.0 m; a bucket is used when the
  objects fit with a gap), recorded in ``FamilyLayout.rows``;
- cluttered tables (1-2 rows plus 2-5 other items: laptop, keyboard, mouse, bowl, vase, wine glass, fruit...);
- small objects (``size_class``: footprint under 10 cm: cups, bottles, glasses, fruit, mice) and large ones
  (footprint over 1 m: tables, couches, beds, tvs) in every scene.

Spec: ``synthetic:family?seed=N&frames=900`` with the room's knobs (``width``, ``height``, ``fps``, ``odom_drift``,
``miss_rate``, ``fp_rate``, ``depth_noise``, ``loop_gap``); ``revolutions`` (1.15) is the number of path cycles
(laps, round trips, sweep cycles) walked in ``frames / fps`` seconds, fewer when the path's speed (0.5-1 m/s)
or yaw-rate limit does not allow them: 300 frames at 30 fps cover about half a lap of a large room, 900 frames
(the benchmark's) the full 1.15. Ground truth as for the room: poses, objects, instance masks, detection ids,
loops (revisits within 0.3 m and 20 degrees, ``loop_gap`` frames apart), plus ``SyntheticDataset.family`` (this
module's ``FamilyLayout``: room, path plan, rows, plain walls).

Everything is a pure function of the seed (the layout) and of (seed, frames, fps, revolutions) (the timing of
the path); the frames are rendered by ``sources.synthetic.SyntheticDataset`` exactly as the room's.
``HELD_OUT_SEEDS`` are the benchmark's scenes (``objslam bench objects --family``) and are never used for tuning;
tune and look at failures on ``DEVELOPMENT_SEEDS``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sources.base import ObjectTruth
from sources.family_paths import PATH_KINDS, PathPlan, path_points, path_poses, plan_path
from sources.scene import _footprint, _inside, _min_distance, _overlap

HELD_OUT_SEEDS: tuple[int, ...] = tuple(range(1000, 1020))  # benchmark scenes: never tune on these
# for tuning and looking at failures (8 until 2026-12-03, 24 until 2026-12-05)
DEVELOPMENT_SEEDS: tuple[int, ...] = tuple(range(36))
SPACING_BUCKETS_M: tuple[float, ...] = (0.3, 0.5, 0.7, 1.0)
_BUCKET_WEIGHTS = (0.35, 0.3, 0.2, 0.15)  # the order buckets are tried in: close spacings first, more often
ROW_LABELS: tuple[str, ...] = ("chair", "cup", "bottle", "book")
CLEARANCE_M = 0.6  # minimum horizontal distance from every camera position to every object footprint
SMALL_M, LARGE_M = 0.10, 1.0  # size classes by the longest side of the footprint
_MARGIN = 0.05  # extra clearance at planning time (tremor)
_GAP = 0.01  # minimum gap between objects
# kind -> (size low, size high): x along a wall / the row / the table's length, y depth, z height
_SIZES: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "table": ((1.2, 0.75, 0.72), (2.0, 1.0, 0.78)),
    "desk": ((1.0, 0.6, 0.72), (1.6, 0.8, 0.76)),
    "chair": ((0.4, 0.42, 0.8), (0.44, 0.48, 0.95)),
    "couch": ((1.6, 0.8, 0.75), (2.3, 0.95, 0.9)),
    "refrigerator": ((0.65, 0.65, 1.7), (0.8, 0.75, 1.9)),
    "bed": ((1.4, 2.0, 0.45), (1.8, 2.1, 0.6)),
    "tv": ((1.0, 0.05, 0.6), (1.4, 0.07, 0.8)),
    "clock": ((0.25, 0.04, 0.25), (0.35, 0.06, 0.35)),
    "potted plant": ((0.3, 0.3, 0.5), (0.5, 0.5, 1.1)),
    "suitcase": ((0.4, 0.22, 0.6), (0.5, 0.28, 0.7)),
    "teddy bear": ((0.22, 0.18, 0.3), (0.3, 0.25, 0.4)),
    "cup": ((0.07, 0.07, 0.08), (0.09, 0.09, 0.095)),
    "bottle": ((0.06, 0.06, 0.22), (0.08, 0.08, 0.3)),
    "wine glass": ((0.06, 0.06, 0.14), (0.08, 0.08, 0.18)),
    "book": ((0.15, 0.21, 0.03), (0.18, 0.25, 0.05)),
    "laptop": ((0.3, 0.22, 0.02), (0.36, 0.25, 0.03)),
    "keyboard": ((0.42, 0.13, 0.02), (0.46, 0.16, 0.03)),
    "mouse": ((0.06, 0.09, 0.035), (0.07, 0.095, 0.04)),
    "bowl": ((0.14, 0.14, 0.06), (0.18, 0.18, 0.08)),
    "vase": ((0.1, 0.1, 0.2), (0.14, 0.14, 0.35)),
    "apple": ((0.07, 0.07, 0.07), (0.09, 0.09, 0.09)),
    "orange": ((0.07, 0.07, 0.07), (0.09, 0.09, 0.09)),
}
_LABELS = {"table": "dining table", "desk": "dining table"}  # kind -> COCO label (default: the kind)
_ROUND = {"cup", "bottle", "wine glass", "bowl", "vase", "apple", "orange", "potted plant"}
_TABLE_ITEMS = ("laptop", "keyboard", "mouse", "bowl", "vase", "wine glass", "apple", "orange", "cup", "bottle", "book")
_WALL_KINDS = ("couch", "refrigerator", "desk", "chair", "tv", "clock", "potted plant", "suitcase", "bed")
_WALL_WEIGHTS = (0.14, 0.1, 0.18, 0.16, 0.1, 0.08, 0.1, 0.06, 0.08)


def size_class(obj: ObjectTruth) -> str:
    """``small`` (footprint's longest side < 10 cm), ``large`` (> 1 m) or ``medium``."""
    side = max(obj.size[0], obj.size[1])
    return "small" if side < SMALL_M else "large" if side > LARGE_M else "medium"


def spacing_bucket(distance_m: float) -> float:
    """The nearest of ``SPACING_BUCKETS_M``."""
    return min(SPACING_BUCKETS_M, key=lambda b: abs(b - distance_m))


@dataclass(frozen=True)
class Row:
    """Same-class objects in a line: their ids in order along it and the nominal centre spacing (m)."""

    label: str
    ids: tuple[int, ...]
    spacing_m: float

    @property
    def bucket(self) -> float:
        return spacing_bucket(self.spacing_m)


@dataclass(frozen=True)
class FamilyLayout:
    """One scene of the family: room box, light, camera path plan, objects (ids from 1) and rows."""

    seed: int
    room: tuple[float, float, float]
    light: tuple[float, float, float]
    path: PathPlan
    plain_walls: bool
    objects: tuple[ObjectTruth, ...]
    rows: tuple[Row, ...] = field(default=())

    def pairs(self) -> list[tuple[int, int, float]]:
        """Neighbouring row members (id a, id b, spacing bucket (m))."""
        return [(a, b, r.bucket) for r in self.rows for a, b in zip(r.ids[:-1], r.ids[1:], strict=True)]


def _rot(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s], [s, c]])


class _Placer:
    """Objects placed one by one, each checked: in the room, on its support, clear of the path and the others."""

    def __init__(self, room: tuple[float, float, float], plan: PathPlan, rng: np.random.Generator) -> None:
        self.room, self.plan, self.rng = room, plan, rng
        self.cams = path_points(plan)
        self.objects: list[ObjectTruth] = []
        self.supports: list[int] = []  # index of the supporting object, -1 floor or wall
        self.rows: list[Row] = []

    def size(self, kind: str) -> tuple[float, float, float]:
        """A random size of ``kind`` (round things: as deep as wide)."""
        lo, hi = _SIZES[kind]
        s = self.rng.uniform(lo, hi)
        if kind in _ROUND:
            s[1] = s[0]
        return float(s[0]), float(s[1]), float(s[2])

    def add(self, kind: str, xy, size, yaw: float, support: int = -1, bottom: float = 0.0) -> int | None:
        """Place an object (on ``support``'s top, else at height ``bottom``); its index, or None if invalid."""
        z0 = bottom if support < 0 else self.objects[support].center[2] + self.objects[support].size[2] / 2.0
        centre = (float(xy[0]), float(xy[1]), float(z0 + size[2] / 2.0))
        obj = ObjectTruth(len(self.objects) + 1, _LABELS.get(kind, kind), centre, tuple(size), float(yaw))
        if not self._valid(obj, support):
            return None
        self.objects.append(obj)
        self.supports.append(support)
        return len(self.objects) - 1

    def _valid(self, obj: ObjectTruth, support: int) -> bool:
        c = np.asarray(obj.center)
        poly = _footprint(c, obj.size, obj.yaw)
        if np.any(poly < 0.005) or np.any(poly > np.array(self.room[:2]) - 0.005):
            return False
        if c[2] + obj.size[2] / 2.0 > self.room[2] - 0.05 or not _seen(self.plan, c[:2]):
            return False
        if _min_distance(self.cams, c, obj.size, obj.yaw) < CLEARANCE_M + _MARGIN:
            return False
        if support >= 0:
            base = self.objects[support]
            if not _inside(poly, np.asarray(base.center), (base.size[0] - 0.04, base.size[1] - 0.04), base.yaw):
                return False
        return not any(k != support and _intersect(obj, other) for k, other in enumerate(self.objects))

    def truncate(self, count: int) -> None:
        del self.objects[count:], self.supports[count:]

    def row(self, kind: str, origin, axis: float, yaw: float, length: float, support: int = -1) -> bool:
        """A row of 2-5 ``kind`` centred at ``origin`` along heading ``axis``, fitting in ``length`` m."""
        size = self.size(kind)
        jitter = 0.04 if kind == "chair" else 0.3 if kind == "book" else np.pi
        extent = float(np.hypot(size[0], size[1]) if kind in _ROUND else size[0] + size[1] * np.sin(jitter))
        spacing = _pick_spacing(self.rng, extent, length)
        if spacing is None:
            return False
        n, s = spacing
        d, perp = np.array([np.cos(axis), np.sin(axis)]), np.array([-np.sin(axis), np.cos(axis)])
        mark = len(self.objects)
        for i in range(n):
            xy = np.asarray(origin) + d * (i - (n - 1) / 2.0) * s + perp * self.rng.uniform(-0.015, 0.015)
            member = tuple(float(v) for v in np.asarray(size) * self.rng.uniform(0.98, 1.02, 3))
            if kind in _ROUND:
                member = (member[0], member[0], member[2])
            if self.add(kind, xy, member, yaw + self.rng.uniform(-jitter, jitter), support) is None:
                self.truncate(mark)
                return False
        self.rows.append(Row(self.objects[mark].label, tuple(o.id for o in self.objects[mark:]), s))
        return True

    def on_top(self, support: int, kind: str, attempts: int = 20) -> bool:
        """An item at a random spot on ``support``'s top."""
        base = self.objects[support]
        for _ in range(attempts):
            local = self.rng.uniform(-0.5, 0.5, 2) * (np.asarray(base.size[:2]) - 0.1)
            xy = np.asarray(base.center[:2]) + _rot(base.yaw) @ local
            if self.add(kind, xy, self.size(kind), self.rng.uniform(-np.pi, np.pi), support) is not None:
                return True
        return False

    def clutter(self, table: int, rows: int) -> None:
        """Rows of cups, bottles or books along the table's length and 2-5 other items on it."""
        t = self.objects[table]
        lanes = [0.0] if rows == 1 or t.size[1] < 0.7 else [-t.size[1] / 4.0, t.size[1] / 4.0]
        if len(lanes) == 1:
            lanes = [self.rng.uniform(-1.0, 1.0) * (t.size[1] / 2.0 - 0.14)]
        for lane in lanes:
            kind = str(self.rng.choice(["cup", "bottle", "book"]))
            for _ in range(4):
                shift = self.rng.uniform(-0.1, 0.1) * t.size[0]
                xy = np.asarray(t.center[:2]) + _rot(t.yaw) @ np.array([shift, lane])
                if self.row(kind, xy, t.yaw, t.yaw, t.size[0] - 2.0 * abs(shift) - 0.06, table):
                    break
        for _ in range(int(self.rng.integers(2, 6))):
            self.on_top(table, str(self.rng.choice(_TABLE_ITEMS)))

    def chairs_along(self, table: int) -> None:
        """Rows of chairs along one or both long sides of a table."""
        t = self.objects[table]
        for side in (-1.0, 1.0):
            if self.rng.random() < 0.3:
                continue
            depth = _SIZES["chair"][1][1]
            local = np.array([self.rng.uniform(-0.1, 0.1), side * (t.size[1] / 2.0 + depth / 2.0 + 0.08)])
            xy = np.asarray(t.center[:2]) + _rot(t.yaw) @ local
            self.row("chair", xy, t.yaw, t.yaw + (np.pi if side > 0 else 0.0), t.size[0] + 0.3)

    def wall_item(self, kind: str, wall: int, attempts: int = 12) -> None:
        """``kind`` against ``wall`` (0 south, 1 east, 2 north, 3 west), facing the room."""
        origin, tangent, normal, length, yaw = _wall(self.room, wall)
        for _ in range(attempts):
            if kind == "chair":
                depth = _SIZES["chair"][1][1]
                xy = origin + tangent * self.rng.uniform(0.3, length - 0.3) + normal * (depth / 2.0 + 0.03)
                if self.row("chair", xy, yaw, yaw, min(length - 0.2, 3.0)):
                    return
                continue
            size = self.size(kind)
            s = self.rng.uniform(size[0] / 2.0 + 0.02, length - size[0] / 2.0 - 0.02)
            xy = origin + tangent * s + normal * (size[1] / 2.0 + 0.01)
            bottom = {"tv": self.rng.uniform(0.9, 1.2), "clock": self.rng.uniform(1.7, 1.95)}.get(kind, 0.0)
            k = self.add(kind, xy, size, yaw + self.rng.uniform(-0.03, 0.03), bottom=bottom)
            if k is not None:
                self.extras(kind, k)
                return

    def free_item(self, kind: str, attempts: int = 25) -> None:
        """``kind`` standing free in the room (a table gets chairs and clutter, a chair is a row of chairs)."""
        w, d = self.room[0], self.room[1]
        for _ in range(attempts):
            xy = np.array([self.rng.uniform(0.4, w - 0.4), self.rng.uniform(0.4, d - 0.4)])
            yaw = float(self.rng.choice([0.0, np.pi / 2.0])) + self.rng.uniform(-0.3, 0.3)
            if kind == "chair":
                if self.row("chair", xy, yaw, yaw, 3.0):
                    return
                continue
            k = self.add(kind, xy, self.size(kind), yaw)
            if k is not None:
                self.extras(kind, k)
                return

    def extras(self, kind: str, k: int) -> None:
        """What stands on a new piece of furniture: clutter and chairs on tables, a bear or book on a couch."""
        if kind in ("table", "desk"):
            if kind == "table":
                self.chairs_along(k)
            self.clutter(k, 1 if kind == "desk" or self.rng.random() < 0.25 else 2)
        elif kind in ("couch", "bed") and self.rng.random() < 0.6:
            self.on_top(k, str(self.rng.choice(["teddy bear", "book"])))


def _pick_spacing(rng: np.random.Generator, extent: float, length: float) -> tuple[int, float] | None:
    """(count 2-5, spacing) of a row of objects ``extent`` long along it in ``length`` m, or None."""
    order = rng.choice(len(SPACING_BUCKETS_M), len(SPACING_BUCKETS_M), replace=False, p=_BUCKET_WEIGHTS)
    for bucket in np.asarray(SPACING_BUCKETS_M)[order]:
        if bucket - 0.02 < extent + 0.015:
            continue
        s = float(np.clip(bucket + rng.uniform(-0.02, 0.02), SPACING_BUCKETS_M[0], SPACING_BUCKETS_M[-1]))
        most = min(5, int((length - extent) // s) + 1)
        if most >= 2:
            return int(rng.integers(2, most + 1)), s
    return None


def _wall(room: tuple[float, float, float], wall: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """(origin, tangent, inward normal, length, yaw) of a wall; yaw turns an object's x along the wall."""
    w, d = room[0], room[1]
    return [
        (np.array([0.0, 0.0]), np.array([1.0, 0.0]), np.array([0.0, 1.0]), w, 0.0),
        (np.array([w, 0.0]), np.array([0.0, 1.0]), np.array([-1.0, 0.0]), d, np.pi / 2.0),
        (np.array([w, d]), np.array([-1.0, 0.0]), np.array([0.0, -1.0]), w, np.pi),
        (np.array([0.0, d]), np.array([0.0, -1.0]), np.array([1.0, 0.0]), d, -np.pi / 2.0),
    ][wall]


def _seen(plan: PathPlan, xy: np.ndarray) -> bool:
    """Whether the path faces ``xy`` at all: not inside an outward lap, not behind a sweep."""
    rel = xy - np.asarray(plan.centre)
    if plan.kind == "outward":
        return bool((rel[0] / plan.axes[0]) ** 2 + (rel[1] / plan.axes[1]) ** 2 > 1.0)
    if plan.kind == "sweep":
        off = (np.arctan2(rel[1], rel[0]) - plan.theta0 + np.pi) % (2.0 * np.pi) - np.pi
        return bool(abs(off) <= plan.look_offset + 0.6)
    return True


def _intersect(a: ObjectTruth, b: ObjectTruth) -> bool:
    """True when two boxes share volume or come within ``_GAP`` of each other horizontally."""
    top = min(a.center[2] + a.size[2] / 2.0, b.center[2] + b.size[2] / 2.0)
    if top - max(a.center[2] - a.size[2] / 2.0, b.center[2] - b.size[2] / 2.0) <= 1e-6:
        return False
    grow = (2.0 * _GAP, 2.0 * _GAP, 0.0)
    pa = _footprint(np.asarray(a.center), tuple(np.add(a.size, grow)), a.yaw)
    return _overlap(pa, _footprint(np.asarray(b.center), b.size, b.yaw))


def _complete(p: _Placer) -> bool:
    """At least two rows, a cluttered table, a small and a large object."""
    on = np.bincount([s for s in p.supports if s >= 0], minlength=len(p.objects))
    tables = [k for k, o in enumerate(p.objects) if o.label == "dining table"]
    sizes = {size_class(o) for o in p.objects}
    return len(p.rows) >= 2 and any(on[k] >= 3 for k in tables) and {"small", "large"} <= sizes


def make_layout(seed: int) -> FamilyLayout:
    """The family scene of ``seed``: room, path plan (kind ``PATH_KINDS[seed % 4]``), objects and rows."""
    rng = np.random.default_rng([seed, 1000])
    room = (float(rng.uniform(4.0, 9.0)), float(rng.uniform(4.0, 9.0)), float(rng.uniform(2.5, 3.0)))
    plain = bool(rng.random() < 0.3)
    plan = plan_path(PATH_KINDS[seed % len(PATH_KINDS)], room, np.random.default_rng([seed, 1001]))
    area = room[0] * room[1]
    for attempt in range(40):
        p = _Placer(room, plan, np.random.default_rng([seed, 1002, attempt]))
        for wall in p.rng.permutation(4):
            length = room[0] if wall % 2 == 0 else room[1]
            for _ in range(int(np.ceil(length / 1.8))):
                kind = str(p.rng.choice(_WALL_KINDS, p=_WALL_WEIGHTS))
                if kind != "bed" or min(room[:2]) >= 6.0:
                    p.wall_item(kind, int(wall))
        free = ["table"] * (1 + int(area > 45 and p.rng.random() < 0.5)) + ["chair"] * int(p.rng.random() < 0.6)
        free += ["potted plant"] * int(p.rng.integers(0, 3)) + ["suitcase"] * int(p.rng.random() < 0.3)
        free += ["couch"] * int(area > 30 and p.rng.random() < 0.3)
        if plan.kind == "inward":  # what inward laps see within depth range is the middle of the room
            free += ["table", "chair", "potted plant"]
        for kind in free:
            p.free_item(kind)
        if _complete(p):
            break
    light = (room[0] / 2.0, room[1] / 2.0, room[2] - 0.15)
    return FamilyLayout(seed, room, light, plan, plain, tuple(p.objects), tuple(p.rows))


def family_poses(layout: FamilyLayout, frames: int, fps: float, cycles: float) -> np.ndarray:
    """True camera-to-world poses (frames, 4, 4) along the layout's path: ``cycles`` laps / trips / sweep cycles."""
    return path_poses(layout.path, frames, fps, cycles, layout.seed)
