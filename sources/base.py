"""The replay-source interface: a sequence of frames plus the ground truth used only for evaluation."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace

import numpy as np

from graph.trajectory import Trajectory, nearest_timestamps
from perception.frame import CameraModel, Frame


def as_box(values: Iterable[float]) -> tuple[float, float, float, float]:
    """(x1, y1, x2, y2) floats of a detection box; ValueError unless there are exactly four values."""
    x1, y1, x2, y2 = (float(v) for v in values)
    return x1, y1, x2, y2


class DatasetError(Exception):
    """A dataset cannot be opened or read; the message is one clear line for the user."""


@dataclass(frozen=True)
class ObjectTruth:
    """A ground-truth object: a yawed 3D box in the world frame (``objects_gt.json``)."""

    id: int
    label: str
    center: tuple[float, float, float]
    size: tuple[float, float, float]
    yaw: float


class Dataset(ABC):
    """A replayable RGB-D sequence. Frame indices are 0-based.

    Ground truth (``ground_truth``, ``objects``, ``loops``, ``instance_mask``) is for evaluation
    only and is never put into the frames sent to the pipeline.
    """

    name: str
    camera: CameraModel

    @abstractmethod
    def __len__(self) -> int: ...

    @abstractmethod
    def frame(self, index: int) -> Frame:
        """Frame ``index`` with colour, depth, and the odometry / detections the dataset provides."""

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self.frame(i)

    @property
    def timestamps(self) -> np.ndarray:
        """Timestamps of all frames, (N,)."""
        return np.array([self.frame(i).timestamp for i in range(len(self))])

    @property
    def ground_truth(self) -> Trajectory | None:
        return None

    @property
    def objects(self) -> list[ObjectTruth] | None:
        return None

    @property
    def loops(self) -> list[tuple[int, int]] | None:
        """True revisit pairs (earlier, later) as 0-based frame indices."""
        return None

    def instance_mask(self, index: int) -> np.ndarray | None:
        """Per-pixel instance ids (0 = none) of frame ``index``, matching ``objects`` ids."""
        return None


def ground_truth_of(dataset: Dataset) -> Trajectory:
    """The dataset's ground-truth trajectory; DatasetError when it has none (benchmarks need it)."""
    truth = dataset.ground_truth
    if truth is None:
        raise DatasetError(f"{dataset.name}: no ground truth")
    return truth


def truth_per_frame(dataset: Dataset) -> np.ndarray:
    """The ground-truth pose of every frame, (N, 4, 4); DatasetError when a frame has none."""
    truth = dataset.ground_truth
    if truth is None:
        raise DatasetError(f"{dataset.name}: no ground truth")
    match = nearest_timestamps(dataset.timestamps, truth.timestamps, 0.01)
    if (match < 0).any():
        raise DatasetError(f"{dataset.name}: {int((match < 0).sum())} frames have no ground-truth pose")
    return truth.poses[match]


class DatasetView(Dataset):
    """Another dataset, passed through: the base of views that change what its frames carry."""

    def __init__(self, inner: Dataset):
        self.inner = inner
        self.name = inner.name
        self.camera = inner.camera

    def __len__(self) -> int:
        return len(self.inner)

    def frame(self, index: int) -> Frame:
        return self.inner.frame(index)

    @property
    def timestamps(self) -> np.ndarray:
        return self.inner.timestamps

    @property
    def ground_truth(self) -> Trajectory | None:
        return self.inner.ground_truth

    @property
    def objects(self) -> list[ObjectTruth] | None:
        return self.inner.objects

    @property
    def loops(self) -> list[tuple[int, int]] | None:
        return self.inner.loops

    def instance_mask(self, index: int) -> np.ndarray | None:
        return self.inner.instance_mask(index)


class WithoutOdometry(DatasetView):
    """A view of a dataset whose frames carry no odometry, so the service runs its own front end."""

    def frame(self, index: int) -> Frame:
        f = self.inner.frame(index)
        f.odometry = None
        return f


class TruthAsOdometry(DatasetView):
    """A view whose frames carry the ground-truth pose as their odometry (a benchmark diagnostic: what the
    graph's loops and landmarks do to a perfect trajectory). Every frame needs a ground-truth pose."""

    def __init__(self, inner: Dataset):
        super().__init__(inner)
        self._poses = truth_per_frame(inner)

    def frame(self, index: int) -> Frame:
        f = self.inner.frame(index)
        f.odometry = self._poses[index].copy()
        return f


class ScaledDepth(DatasetView):
    """A view whose depth is read with a calibrated scale: metric depth x ``factor`` (the camera's raw units
    per metre divided by it), e.g. the factor ``objslam calibrate depth-scale`` measured."""

    def __init__(self, inner: Dataset, factor: float):
        super().__init__(inner)
        if not factor > 0:
            raise DatasetError(f"depth scale factor must be positive, got {factor}")
        self.camera = replace(inner.camera, depth_scale=inner.camera.depth_scale / factor)

    def frame(self, index: int) -> Frame:
        f = self.inner.frame(index)
        f.camera = self.camera
        return f


class Subset(DatasetView):
    """A view of some of another dataset's frames, in order: every ``stride``-th (a keyframe-only stream with
    wide baselines) or a random ``drop`` fraction left out (a busy receiver). The frames keep their own
    ``seq`` and ``index``, so loop records and ground truth still name the original frames."""

    def __init__(self, inner: Dataset, indices: np.ndarray, label: str):
        super().__init__(inner)
        self.indices = np.asarray(indices, dtype=np.int64)
        if len(self.indices) == 0:
            raise DatasetError(f"{inner.name}: the {label} view has no frames")
        self.name = f"{inner.name}[{label}]"

    @classmethod
    def strided(cls, inner: Dataset, stride: int) -> Subset:
        """Every ``stride``-th frame, from the first."""
        if stride < 1:
            raise DatasetError(f"stride must be a positive integer, got {stride}")
        return cls(inner, np.arange(0, len(inner), stride), f"stride={stride}")

    @classmethod
    def dropped(cls, inner: Dataset, fraction: float, seed: int = 0) -> Subset:
        """The frames left when each one after the first is dropped with probability ``fraction`` (seeded)."""
        if not 0.0 <= fraction < 1.0:
            raise DatasetError(f"drop must be a fraction in [0, 1), got {fraction}")
        keep = np.random.default_rng([seed, 53]).random(len(inner)) >= fraction
        keep[0] = True
        return cls(inner, np.nonzero(keep)[0], f"drop={fraction:g},seed={seed}")

    def __len__(self) -> int:
        return len(self.indices)

    def frame(self, index: int) -> Frame:
        if not 0 <= index < len(self):
            raise IndexError(index)
        return self.inner.frame(int(self.indices[index]))

    @property
    def timestamps(self) -> np.ndarray:
        return self.inner.timestamps[self.indices]

    def instance_mask(self, index: int) -> np.ndarray | None:
        return self.inner.instance_mask(int(self.indices[index]))
