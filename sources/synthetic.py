"""Deterministic synthetic RGB-D replay source: a textured room with COCO objects seen by a handheld camera.

The scene (``room``) is a 6 x 5 x 2.6 m room (world z up, floor z = 0) with rich procedural textures on
floor, ceiling and walls, and about a dozen yawed-box objects (table with three cups, laptop and bottle,
chairs, couch with a book, tv, plant, refrigerator) jittered from the seed. The camera orbits the room
centre looking outward for more than one turn, so late frames revisit early viewpoints.

Each frame carries colour, Kinect-like noisy depth (mm), drifting odometry and simulated detections.
Ground truth for evaluation: ``ground_truth`` (true camera-to-world poses), ``objects``, ``loops``,
``instance_mask(i)``, and ``detection_instance_ids(i)`` (the true instance id of each of frame i's
detections, 0 for false positives). None of it enters the frames.
Everything is a pure function of the parameters and (seed, frame index).

Spec: ``synthetic:room?seed=0&frames=300&width=640&height=480&fps=30`` plus optional knobs
``odom_drift`` (1.0 = ~2 mm / 0.05 deg per-frame noise and 0.02 deg/frame yaw bias), ``miss_rate`` (0.05),
``fp_rate`` (0.05 false positives per frame), ``depth_noise`` (1.0 = Kinect sigma), ``loop_gap``
(100 frames between loop pairs), ``revolutions`` (1.15 turns over the sequence) and the detector's errors
(``sources.detector_errors``): ``box_noise`` (0.025 of a box's size per side), ``confusion`` (0) and
``part_boxes`` (0).

``synthetic:blank?seed=N&...`` (same knobs) is the room with plain painted walls and ceiling, whose camera looks
up at them for a stretch of the sequence (``scene.BLANK_STRETCH``): no feature and one or two planes in view,
where tracking must be lost, not invented.

``synthetic:family?seed=N&...`` (same knobs) is a randomized scene per seed instead, rendered the same way: room
size, furniture, rows of same-class objects, cluttered tables, plain walls and the camera path kind all drawn
from the seed (``sources.scene_family``; its layout in ``SyntheticDataset.family``).
"""

from __future__ import annotations

from typing import Any
from urllib.parse import parse_qsl, urlsplit

import numpy as np

from perception.frame import CameraModel, Detection, Frame, Intrinsics
from sources import detector_errors, family_render, scene, scene_family
from sources.base import Dataset, DatasetError, ObjectTruth, Trajectory, as_box
from sources.raycast import (
    Render,
    Renderer,
    Surface,
    box_surfaces,
    object_texture,
    room_surfaces,
    surface_texture,
)

SCENES = ("room", "family", "blank")
MIN_DEPTH_M, MAX_DEPTH_M = 0.4, 4.0
_COLOURS: dict[str, tuple[int, int, int]] = {
    "dining table": (150, 100, 60),
    "cup": (200, 70, 60),
    "laptop": (70, 75, 85),
    "bottle": (60, 150, 90),
    "chair": (120, 80, 150),
    "couch": (60, 90, 160),
    "book": (200, 170, 60),
    "tv": (40, 40, 45),
    "potted plant": (50, 140, 50),
    "refrigerator": (215, 215, 220),
}


def kinect_depth(z: np.ndarray, gauss: np.ndarray, rng: np.random.Generator, noise: float = 1.0) -> np.ndarray:
    """Noisy uint16 depth (mm) from true depth (m): sigma(z) of Nguyen et al. 2012, range limits, edge dropouts.

    ``gauss`` is a bank of standard normals; a random window of it is the frame's noise field.
    """
    start = int(rng.integers(0, len(gauss) - z.size + 1))
    sigma = np.float32(noise) * (np.float32(0.0012) + np.float32(0.0019) * np.square(z - np.float32(0.4)))
    mm = np.rint((z + gauss[start : start + z.size].reshape(z.shape) * sigma) * np.float32(1000.0))
    valid = (z >= MIN_DEPTH_M) & (z <= MAX_DEPTH_M)
    edge = np.zeros(z.shape, bool)
    jump_x = np.abs(z[:, 1:] - z[:, :-1]) > 0.04 * z[:, 1:]
    jump_y = np.abs(z[1:] - z[:-1]) > 0.04 * z[1:]
    edge[:, 1:] |= jump_x
    edge[:, :-1] |= jump_x
    edge[1:] |= jump_y
    edge[:-1] |= jump_y
    ys, xs = np.nonzero(edge)
    drop = rng.random(len(ys)) < 0.4
    valid[ys[drop], xs[drop]] = False
    return np.where(valid, np.clip(mm, 0, 65534), 0).astype(np.uint16)


class SyntheticDataset(Dataset):
    """The synthetic room scene as a replay source (see the module docstring)."""

    def __init__(
        self,
        scene_name: str = "room",
        seed: int = 0,
        frames: int = 300,
        width: int = 640,
        height: int = 480,
        fps: float = 30.0,
        odom_drift: float = 1.0,
        miss_rate: float = 0.05,
        fp_rate: float = 0.05,
        depth_noise: float = 1.0,
        loop_gap: int = 100,
        revolutions: float = 1.15,
        box_noise: float = 0.025,
        confusion: float = 0.0,
        part_boxes: float = 0.0,
    ) -> None:
        values = {"seed": seed, "frames": frames, "width": width, "height": height, "fps": fps}
        noise = {"odom_drift": odom_drift, "miss_rate": miss_rate, "fp_rate": fp_rate, "depth_noise": depth_noise}
        noise |= {"box_noise": box_noise, "confusion": confusion, "part_boxes": part_boxes}
        _check(scene_name, {**values, **noise, "loop_gap": loop_gap, "revolutions": revolutions})
        self.name = f"synthetic/{scene_name}"
        self.seed, self.fps, self.loop_gap = int(seed), float(fps), int(loop_gap)
        self.miss_rate, self.fp_rate, self.depth_noise = float(miss_rate), float(fp_rate), float(depth_noise)
        self.box_noise, self.confusion, self.part_boxes = float(box_noise), float(confusion), float(part_boxes)
        f = 525.0 * width / 640.0
        self.camera = CameraModel(Intrinsics(f, f, (width - 1) / 2.0, (height - 1) / 2.0), width, height, 1000.0)
        self.family: scene_family.FamilyLayout | None = None
        self._poses, self._objects, surfaces = self._layout(scene_name, frames, revolutions)
        self._odometry = scene.drifting_odometry(self._poses, self.seed, float(odom_drift))
        self._labels = sorted({o.label for o in self._objects})
        self.min_pixels = max(20, round(400 * width * height / (640 * 480)))
        self.min_side = 0.04 * min(width, height)
        self._renderer = Renderer(surfaces, self.camera.color, width, height)
        n_pix = width * height
        self._gauss = np.random.default_rng([self.seed, 41]).standard_normal(3 * n_pix, dtype=np.float32)
        self._cache: dict[int, Render] = {}
        self._loops: list[tuple[int, int]] | None = None

    def _layout(
        self, name: str, frames: int, revolutions: float
    ) -> tuple[np.ndarray, list[ObjectTruth], list[Surface]]:
        """True poses, objects and surfaces of scene ``name`` (``family``: its layout is kept in ``self.family``)."""
        if name == "family":
            self.family = scene_family.make_layout(self.seed)
            poses = scene_family.family_poses(self.family, frames, self.fps, revolutions)
            return poses, list(self.family.objects), family_render.family_surfaces(self.family, _COLOURS)
        poses = scene.orbit_trajectory(frames, self.fps, self.seed, revolutions)
        objects = scene.place_objects(self.seed, poses[:, :3, 3])
        if name == "blank":  # plain walls and ceiling; for a while the camera sees nothing else
            first, last = (round(f * frames) for f in scene.BLANK_STRETCH)
            return (
                scene.look_up(poses, first, last, scene.BLANK_PITCH_RAD),
                objects,
                _surfaces(self.seed, objects, True),
            )
        return poses, objects, _surfaces(self.seed, objects)

    def __len__(self) -> int:
        """Number of frames."""
        return len(self._poses)

    @property
    def timestamps(self) -> np.ndarray:
        """Frame times ``i / fps`` in seconds, (N,)."""
        return np.arange(len(self)) / self.fps

    @property
    def ground_truth(self) -> Trajectory:
        """True camera-to-world poses of all frames."""
        return Trajectory(self.timestamps, self._poses.copy())

    @property
    def objects(self) -> list[ObjectTruth]:
        """True object boxes, ids from 1 (matching ``instance_mask``)."""
        return list(self._objects)

    @property
    def loops(self) -> list[tuple[int, int]]:
        """Sorted true revisits (i, j): j - i >= loop_gap, poses within 0.3 m and 20 degrees."""
        if self._loops is None:
            self._loops = scene.find_loops(self._poses, self.loop_gap)
        return list(self._loops)

    @property
    def surfaces(self) -> list:
        """The rendered scene's surfaces (walls, floor and ceiling first, then the objects'); evaluation only."""
        return list(self._renderer.surfaces)

    def instance_mask(self, index: int) -> np.ndarray:
        """Per-pixel object id (uint16, 0 = room) of the nearest surface in frame ``index``."""
        return self._render(index).ids.copy()

    def detection_instance_ids(self, index: int) -> list[int]:
        """The true object id of each detection of frame ``index`` (0: a false positive); evaluation only."""
        return [int(i) for i in self._detections(index, self._render(index))[1]]

    def frame(self, index: int) -> Frame:
        """Frame ``index``: colour, noisy depth, odometry, detections."""
        r = self._render(index)
        rng = np.random.default_rng([self.seed, index, 1])
        depth = kinect_depth(r.depth, self._gauss, rng, self.depth_noise)
        dets, _ = self._detections(index, r)
        return Frame(
            timestamp=index / self.fps,
            seq=index,
            frame_id=f"{self.name}/{index:06d}",
            camera=self.camera,
            rgb=r.rgb.copy(),
            depth=depth,
            odometry=self._odometry[index].copy(),
            detections=dets,
            index=index,
        )

    def _render(self, index: int) -> Render:
        """The ray-cast view of frame ``index`` (the two most recent are cached)."""
        if not 0 <= index < len(self):
            raise IndexError(f"frame {index} out of range [0, {len(self)})")
        if index not in self._cache:
            if len(self._cache) >= 2:
                self._cache.pop(next(iter(self._cache)))
            self._cache[index] = self._renderer.render(self._poses[index])
        return self._cache[index]

    def _detections(self, index: int, r: Render) -> tuple[list[Detection], list[int]]:
        """Simulated detector output from the visible instance masks, sorted by score, with true ids."""
        rng = np.random.default_rng([self.seed, index, 2])
        errors = np.random.default_rng([self.seed, index, 3])  # detector_errors' own stream
        w, h = self.camera.width, self.camera.height
        found: list[tuple[Detection, int]] = []
        for obj in self._objects:
            box_count = _visible_box(r, obj.id)
            miss = rng.random() < self.miss_rate
            jitter = np.clip(rng.standard_normal(4), -2.5, 2.5) * self.box_noise
            noise = rng.normal(0.0, 0.04)
            if box_count is None or miss:
                continue
            (x1, y1, x2, y2), count = box_count
            if count < self.min_pixels or min(x2 - x1, y2 - y1) < self.min_side:
                continue
            bw, bh = x2 - x1, y2 - y1
            box = np.array([x1, y1, x2, y2]) + jitter * np.array([bw, bh, bw, bh])
            box = np.clip(detector_errors.part_box(box, errors, self.part_boxes), 0.0, [w, h, w, h])
            score = float(np.clip(0.45 + 0.5 * (1.0 - np.exp(-count / (3.0 * self.min_pixels))) + noise, 0.4, 0.99))
            label = detector_errors.confused(obj.label, errors, self.confusion)
            found.append((Detection(label, score, as_box(box)), obj.id))
        for _ in range(rng.poisson(self.fp_rate)):
            found.append((self._false_positive(rng), 0))
        found.sort(key=lambda d: -d[0].score)
        return [d for d, _ in found], [i for _, i in found]

    def _false_positive(self, rng: np.random.Generator) -> Detection:
        """A plausible box with a random scene label and a low-ish score."""
        w, h = self.camera.width, self.camera.height
        bw, bh = rng.uniform(0.06, 0.3) * w, rng.uniform(0.06, 0.3) * h
        x1, y1 = rng.uniform(0, w - bw), rng.uniform(0, h - bh)
        label = self._labels[int(rng.integers(len(self._labels)))]
        return Detection(label, float(rng.uniform(0.4, 0.7)), (float(x1), float(y1), float(x1 + bw), float(y1 + bh)))


def _visible_box(r: Render, obj_id: int) -> tuple[tuple[int, int, int, int], int] | None:
    """Bounding box [x1, y1, x2, y2) and pixel count of an instance's visible mask, or None."""
    if obj_id not in r.rects:
        return None
    y0, y1, x0, x1 = r.rects[obj_id]
    m = r.ids[y0:y1, x0:x1] == obj_id
    rows, cols = np.nonzero(m.any(1))[0], np.nonzero(m.any(0))[0]
    if len(rows) == 0:
        return None
    return (x0 + int(cols[0]), y0 + int(rows[0]), x0 + int(cols[-1]) + 1, y0 + int(rows[-1]) + 1), int(m.sum())


def _surfaces(seed: int, objects: list[ObjectTruth], plain: bool = False) -> list[Surface]:
    """Lit, textured room faces (walls and ceiling ``plain`` painted, the floor textured) followed by the faces
    of every object (one distinct texture each)."""
    light = np.asarray(scene.LIGHT)

    def room_texture(k: int, width_m: float, height_m: float) -> np.ndarray:
        """Texture of room face ``k`` (4 is the floor)."""
        texture = family_render.plain_texture if plain and k != 4 else surface_texture
        return texture(np.random.default_rng([seed, 31, k]), width_m, height_m)

    out = room_surfaces(scene.ROOM_SIZE, light, room_texture)
    for obj in objects:
        rng = np.random.default_rng([seed, 37, obj.id])
        colour = np.array(_COLOURS.get(obj.label, (128, 128, 128)), float) * rng.uniform(0.75, 1.25, 3)
        texture = object_texture(rng, max(obj.size), colour + rng.normal(0.0, 20.0, 3))
        out.extend(box_surfaces(obj, texture, light, rng))
    return out


_LIMITS: dict[str, tuple[float, float]] = {
    "seed": (0, np.inf),
    "frames": (2, 1_000_000),
    "width": (32, 4096),
    "height": (32, 4096),
    "fps": (1e-3, 1e4),
    "odom_drift": (0.0, 100.0),
    "miss_rate": (0.0, 1.0),
    "fp_rate": (0.0, 20.0),
    "depth_noise": (0.0, 100.0),
    "loop_gap": (1, np.inf),
    "revolutions": (0.01, 10.0),
    "box_noise": (0.0, 0.3),
    "confusion": (0.0, 1.0),
    "part_boxes": (0.0, 1.0),
}


def _check(name: str, values: dict[str, float]) -> None:
    """Raise DatasetError for an unknown scene or an out-of-range parameter."""
    if name not in SCENES:
        raise DatasetError(f"unknown synthetic scene {name!r}; available: {', '.join(SCENES)}")
    for key, value in values.items():
        lo, hi = _LIMITS[key]
        if not (np.isfinite(value) and lo <= value <= hi):
            raise DatasetError(f"synthetic parameter {key}={value} is out of range [{lo}, {hi}]")


_PARAMS: dict[str, type] = {
    "seed": int,
    "frames": int,
    "width": int,
    "height": int,
    "fps": float,
    "odom_drift": float,
    "miss_rate": float,
    "fp_rate": float,
    "depth_noise": float,
    "loop_gap": int,
    "revolutions": float,
    "box_noise": float,
    "confusion": float,
    "part_boxes": float,
}


def parse_synthetic_spec(spec: str) -> SyntheticDataset:
    """A dataset from ``synthetic:NAME?seed=N&frames=N&width=W&height=H&fps=F&odom_drift=..&miss_rate=..``."""
    parts = urlsplit(spec)
    if parts.scheme != "synthetic":
        raise DatasetError(f"not a synthetic spec: {spec!r} (expected synthetic:NAME?key=value&...)")
    name = (parts.netloc or parts.path).strip("/")
    try:
        pairs = parse_qsl(parts.query, keep_blank_values=True, strict_parsing=bool(parts.query))
    except ValueError:
        raise DatasetError(f"malformed synthetic parameters {parts.query!r} (expected key=value&...)") from None
    kwargs: dict[str, Any] = {}  # each value of its parameter's type (_PARAMS)
    for key, raw in pairs:
        if key not in _PARAMS:
            raise DatasetError(f"unknown synthetic parameter {key!r}; known: {', '.join(_PARAMS)}")
        if key in kwargs:
            raise DatasetError(f"synthetic parameter {key!r} given twice")
        try:
            kwargs[key] = _PARAMS[key](raw)
        except ValueError:
            raise DatasetError(f"synthetic parameter {key}={raw!r} is not a valid {_PARAMS[key].__name__}") from None
    return SyntheticDataset(name, **kwargs)
