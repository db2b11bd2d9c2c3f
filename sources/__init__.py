"""Replay sources: TUM-format directories and the synthetic scene simulator."""

from __future__ import annotations

from pathlib import Path

from sources.base import (
    Dataset,
    DatasetError,
    ObjectTruth,
    ScaledDepth,
    Trajectory,
    TruthAsOdometry,
    WithoutOdometry,
    ground_truth_of,
    truth_per_frame,
)

__all__ = [
    "Dataset",
    "DatasetError",
    "ObjectTruth",
    "ScaledDepth",
    "Trajectory",
    "TruthAsOdometry",
    "WithoutOdometry",
    "ground_truth_of",
    "open_dataset",
    "truth_per_frame",
]


def open_dataset(
    spec: str, camera_overrides: dict[str, float] | None = None, camera_defaults: dict[str, float] | None = None
) -> Dataset:
    """A dataset from ``synthetic:NAME?...`` or a directory path; a directory without camera files uses the
    ``camera_overrides`` (command-line flags) over the ``camera_defaults`` (the ``camera`` settings)."""
    if spec.startswith("synthetic:"):
        from sources.synthetic import parse_synthetic_spec

        return parse_synthetic_spec(spec)
    from sources.tum import TumDataset

    return TumDataset(Path(spec), camera_overrides, camera_defaults)
