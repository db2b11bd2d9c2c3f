"""Replay sources: TUM-format directories and the synthetic scene simulator."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import parse_qsl, urlencode

from sources.base import (
    Dataset,
    DatasetError,
    ObjectTruth,
    ScaledDepth,
    Subset,
    Trajectory,
    TruthAsOdometry,
    WithoutOdometry,
    ground_truth_of,
    truth_per_frame,
)

if TYPE_CHECKING:
    from sources.ros2.pairing import RosTopics

__all__ = [
    "Dataset",
    "DatasetError",
    "ObjectTruth",
    "ScaledDepth",
    "Subset",
    "Trajectory",
    "TruthAsOdometry",
    "WithoutOdometry",
    "ground_truth_of",
    "open_dataset",
    "split_view_options",
    "truth_per_frame",
    "with_view",
]


VIEW_OPTIONS = ("stride", "drop", "drop_seed")
"""Spec options of any dataset (``PATH?stride=30``, ``synthetic:room?seed=1&drop=0.3``): a ``Subset`` of its
frames, every ``stride``-th and/or with a random ``drop`` fraction left out (seeded by ``drop_seed``)."""


def open_dataset(
    spec: str,
    camera_overrides: dict[str, float] | None = None,
    camera_defaults: dict[str, float] | None = None,
    ros_topics: RosTopics | None = None,
) -> Dataset:
    """A dataset from ``synthetic:NAME?...``, a directory path or a rosbag2 recording, optionally
    ``?stride=N&drop=F&drop_seed=S`` (``VIEW_OPTIONS``); a directory without camera files uses the
    ``camera_overrides`` (command-line flags) over the ``camera_defaults`` (the ``camera`` settings); a rosbag2
    recording (a directory with ``metadata.yaml``, or one ``.mcap`` / ``.db3`` file) is read on ``ros_topics``."""
    spec, view = split_view_options(spec)
    dataset: Dataset
    if spec.startswith("synthetic:"):
        from sources.synthetic import parse_synthetic_spec

        dataset = parse_synthetic_spec(spec)
    elif _is_rosbag(Path(spec)):
        from sources.ros2.rosbag import RosbagDataset

        if ros_topics is None:
            raise DatasetError(
                f"{spec} is a rosbag2 recording: name its topics with --rgb-topic, --depth-topic and "
                "--camera-info-topic (and --odom-topic / --detections-topic for odometry and detections)"
            )
        dataset = RosbagDataset(Path(spec), ros_topics)
    else:
        from sources.tum import TumDataset

        dataset = TumDataset(Path(spec), camera_overrides, camera_defaults)
    return with_view(dataset, **view)


def _is_rosbag(path: Path) -> bool:
    """A rosbag2 directory (with ``metadata.yaml``) or a single ``.mcap`` / ``.db3`` storage file (checked here,
    not in ``sources.ros2``, so other datasets open without importing rosbags)."""
    is_dir = path.is_dir() and (path / "metadata.yaml").is_file()
    return is_dir or (path.is_file() and path.suffix in (".mcap", ".db3"))


def split_view_options(spec: str) -> tuple[str, dict[str, float]]:
    """``spec`` without its ``VIEW_OPTIONS``, and their values; DatasetError for a malformed value."""
    base, sep, query = spec.partition("?")
    if not sep:
        return spec, {}
    try:
        pairs = parse_qsl(query, keep_blank_values=True, strict_parsing=True)
    except ValueError:
        raise DatasetError(f"malformed dataset options {query!r} (expected key=value&...)") from None
    rest = [(k, v) for k, v in pairs if k not in VIEW_OPTIONS]
    view: dict[str, float] = {}
    for key, raw in pairs:
        if key in VIEW_OPTIONS:
            try:
                view[key] = float(raw)
            except ValueError:
                raise DatasetError(f"dataset option {key}={raw!r} is not a number") from None
    return (f"{base}?{urlencode(rest)}" if rest else base), view


def with_view(dataset: Dataset, stride: float = 1, drop: float = 0.0, drop_seed: float = 0) -> Dataset:
    """``dataset`` strided, then thinned by random drops (``Subset``); itself when neither is asked for."""
    if stride != int(stride) or drop_seed != int(drop_seed):
        raise DatasetError(f"stride and drop_seed must be integers, got {stride:g} and {drop_seed:g}")
    if stride != 1:
        dataset = Subset.strided(dataset, int(stride))
    if drop:
        dataset = Subset.dropped(dataset, drop, int(drop_seed))
    return dataset
