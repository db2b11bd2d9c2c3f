"""TUM RGB-D directories with objslam's extensions (SPEC section 3), including the 7-Scenes layout."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np
from pydantic import BaseModel

from graph.geometry import pose_from_tum
from graph.trajectory import nearest_timestamps
from perception.frame import CameraModel, Detection, Frame, Intrinsics
from sources.base import Dataset, DatasetError, ObjectTruth, Trajectory, as_box

log = logging.getLogger(__name__)

MAX_TIME_DIFF_S = 0.02


class CameraDefaults(BaseModel):
    """Camera of a dataset directory without camera files (camera.json, a 7-Scenes camera-intrinsics.txt);
    the `run` / `replay` flags --fx, --fy, --cx, --cy, --depth-scale override it. Defaults: TUM's."""

    fx: float = 525.0
    fy: float = 525.0
    cx: float = 319.5
    cy: float = 239.5
    depth_scale: float = 5000.0


TUM_DEFAULT = CameraDefaults().model_dump()  # the `camera` settings' defaults: TUM's


def read_index(path: Path) -> list[tuple[float, str]]:
    """``timestamp path`` lines of rgb.txt / depth.txt (``#`` comments skipped)."""
    rows = []
    for line in _data_lines(path):
        parts = line.split()
        if len(parts) < 2:
            raise DatasetError(f"{path}: expected 'timestamp path', got {line!r}")
        rows.append((_float(parts[0], path), parts[1]))
    return rows


def read_trajectory(path: Path) -> Trajectory:
    """A TUM trajectory file ``t tx ty tz qx qy qz qw``."""
    rows = []
    for line in _data_lines(path):
        parts = line.split()
        if len(parts) != 8:
            raise DatasetError(f"{path}: expected 8 columns, got {len(parts)} in {line!r}")
        rows.append([_float(p, path) for p in parts])
    if not rows:
        return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
    arr = np.asarray(rows)
    return Trajectory(arr[:, 0], np.stack([pose_from_tum(r[1:]) for r in arr]))


class TumDataset(Dataset):
    """A TUM-layout directory: frames from associations.txt (or rgb.txt + depth.txt)."""

    def __init__(
        self,
        root: Path,
        camera_overrides: dict[str, float] | None = None,
        camera_defaults: dict[str, float] | None = None,
    ):
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(f"dataset directory not found: {self.root}")
        self.name = self.root.name
        self.camera = load_camera(self.root, camera_overrides or {}, camera_defaults)
        self._times, self._rgb, self._depth = self._load_frames()
        self._odometry = self._load_odometry()
        self._detections = self._load_detections()

    def __len__(self) -> int:
        return len(self._times)

    @property
    def timestamps(self) -> np.ndarray:
        return self._times.copy()

    def frame(self, index: int) -> Frame:
        if not 0 <= index < len(self):
            raise IndexError(index)
        rgb = cv2.imread(str(self.root / self._rgb[index]), cv2.IMREAD_COLOR)
        if rgb is None:
            raise DatasetError(f"cannot read colour image {self._rgb[index]}")
        depth = cv2.imread(str(self.root / self._depth[index]), cv2.IMREAD_UNCHANGED)
        if depth is None or depth.dtype != np.uint16 or depth.ndim != 2:
            raise DatasetError(f"depth image {self._depth[index]} is not a 16-bit single-channel PNG")
        depth = depth.copy()
        depth[depth == 65535] = 0
        return Frame(
            timestamp=float(self._times[index]),
            seq=index,
            frame_id=f"{self.name}/{index:06d}",
            camera=self.camera,
            rgb=cv2.cvtColor(rgb, cv2.COLOR_BGR2RGB),
            depth=depth,
            odometry=None if self._odometry is None else self._odometry[index],
            detections=None if self._detections is None else self._detections[index],
            index=index,
        )

    @property
    def ground_truth(self) -> Trajectory | None:
        path = self.root / "groundtruth.txt"
        return read_trajectory(path) if path.is_file() else None

    @property
    def objects(self) -> list[ObjectTruth] | None:
        path = self.root / "objects_gt.json"
        if not path.is_file():
            return None
        items = _read_json(path)
        return [
            ObjectTruth(int(o["id"]), str(o["label"]), tuple(o["center"]), tuple(o["size"]), float(o.get("yaw", 0.0)))
            for o in items
        ]

    @property
    def loops(self) -> list[tuple[int, int]] | None:
        path = self.root / "loops_gt.json"
        return [(int(i), int(j)) for i, j in _read_json(path)] if path.is_file() else None

    def instance_mask(self, index: int) -> np.ndarray | None:
        path = self.root / "instances" / f"{index:06d}.png"
        return cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if path.is_file() else None

    def _load_frames(self) -> tuple[np.ndarray, list[str], list[str]]:
        assoc = self.root / "associations.txt"
        if assoc.is_file():
            rows = [line.split() for line in _data_lines(assoc)]
            if any(len(r) < 4 for r in rows):
                raise DatasetError(f"{assoc}: expected 't_rgb rgb t_depth depth' lines")
            times = np.array([_float(r[0], assoc) for r in rows])
            return times, [r[1] for r in rows], [r[3] for r in rows]
        rgb_txt, depth_txt = self.root / "rgb.txt", self.root / "depth.txt"
        if not (rgb_txt.is_file() and depth_txt.is_file()):
            raise DatasetError(f"{self.root} has neither associations.txt nor rgb.txt + depth.txt")
        rgb, depth = read_index(rgb_txt), read_index(depth_txt)
        match = nearest_timestamps(np.array([t for t, _ in rgb]), np.array([t for t, _ in depth]), MAX_TIME_DIFF_S)
        keep = [i for i, j in enumerate(match) if j >= 0]
        if not keep:
            raise DatasetError(f"{self.root}: no rgb frame has a depth frame within {MAX_TIME_DIFF_S} s")
        return (np.array([rgb[i][0] for i in keep]), [rgb[i][1] for i in keep], [depth[match[i]][1] for i in keep])

    def _load_odometry(self) -> list[np.ndarray | None] | None:
        path = self.root / "odometry.txt"
        if not path.is_file():
            return None
        traj = read_trajectory(path)
        match = nearest_timestamps(self._times, traj.timestamps, MAX_TIME_DIFF_S)
        return [traj.poses[j] if j >= 0 else None for j in match]

    def _load_detections(self) -> list[list[Detection]] | None:
        path = self.root / "detections.jsonl"
        if not path.is_file():
            return None
        times, lists = [], []
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if not line.strip():
                continue
            try:
                row = json.loads(line)
                dets = [Detection(str(d["label"]), float(d["score"]), as_box(d["box"])) for d in row["detections"]]
                times.append(float(row["t"]))
            except (ValueError, KeyError, TypeError) as exc:
                raise DatasetError(f"{path}:{n}: bad detections line ({exc})") from None
            lists.append(dets)
        match = nearest_timestamps(self._times, np.array(times), MAX_TIME_DIFF_S)
        return [lists[j] if j >= 0 else [] for j in match]


def load_camera(root: Path, overrides: dict[str, float], defaults: dict[str, float] | None = None) -> CameraModel:
    """camera.json, else the 7-Scenes ``camera-intrinsics.txt`` convention, else the flags (``overrides``) over
    the configured ``defaults`` (the ``camera`` settings) over the TUM defaults. Flags a camera file makes
    moot are reported, not silently dropped."""
    path = root / "camera.json"
    if path.is_file():
        _report_ignored(overrides, set(), path)
        return _camera_from_json(_read_json(path), path)
    if (root / "camera-intrinsics.txt").is_file():
        _report_ignored(overrides, {"depth_scale"}, root / "camera-intrinsics.txt")
        return _seven_scenes_camera(root / "camera-intrinsics.txt", overrides)
    values = {**TUM_DEFAULT, **(defaults or {}), **overrides}
    return CameraModel(
        Intrinsics(values["fx"], values["fy"], values["cx"], values["cy"]),
        int(overrides.get("width", 640)),
        int(overrides.get("height", 480)),
        values["depth_scale"],
    )


def _report_ignored(overrides: dict[str, float], used: set[str], path: Path) -> None:
    ignored = sorted(set(overrides) - used)
    if ignored:
        log.warning(
            "%s defines the camera: %s not applied (edit or write camera.json instead)",
            path,
            ", ".join("--" + k.replace("_", "-") for k in ignored),
        )


def _camera_from_json(obj: dict, path: Path) -> CameraModel:
    try:
        color = Intrinsics(*(float(obj[k]) for k in ("fx", "fy", "cx", "cy")))
        depth_k = obj.get("depth_K")
        depth = None if depth_k is None else Intrinsics(*(float(depth_k[k]) for k in ("fx", "fy", "cx", "cy")))
        extr = None if obj.get("depth_to_color") is None else np.asarray(obj["depth_to_color"], dtype=float)
        if extr is not None and extr.shape != (4, 4):
            raise ValueError("depth_to_color must be 4x4")
        return CameraModel(
            color,
            int(obj.get("width", 640)),
            int(obj.get("height", 480)),
            float(obj.get("depth_scale", 5000.0)),
            depth,
            extr,
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise DatasetError(f"{path}: invalid camera.json ({exc})") from None


def _seven_scenes_camera(path: Path, overrides: dict[str, float]) -> CameraModel:
    """7-Scenes / 3DMatch: K is the depth camera's, depth in mm; colour is unregistered.

    The colour model is the empirical one of the data README: p_color = 0.90 (p_depth - c) + c + (-8, -2) px
    at about 1.8 m, i.e. a colour focal length of 0.9 x 585 px and an IR-to-RGB offset of about
    (-2.7, -0.7) cm. It is an estimate, not a calibration; camera.json overrides it.
    """
    K = np.loadtxt(path)
    if K.shape != (3, 3):
        raise DatasetError(f"{path}: expected a 3x3 intrinsic matrix")
    depth = Intrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    f_color = 0.9 * depth.fx
    color = Intrinsics(f_color, f_color, depth.cx, depth.cy)
    depth_to_color = np.eye(4)
    depth_to_color[:3, 3] = [-8.0 * 1.8 / f_color, -2.0 * 1.8 / f_color, 0.0]
    scale = float(overrides.get("depth_scale", 1000.0))
    return CameraModel(color, 640, 480, scale, depth, depth_to_color)


def _data_lines(path: Path) -> list[str]:
    try:
        text = path.read_text()
    except OSError as exc:
        raise DatasetError(f"cannot read {path}: {exc.strerror}") from None
    return [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DatasetError(f"cannot read {path}: {exc}") from None


def _float(text: str, path: Path) -> float:
    try:
        return float(text)
    except ValueError:
        raise DatasetError(f"{path}: {text!r} is not a number") from None
