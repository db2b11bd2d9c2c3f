"""A large object seen in parts (``perception.footprint``): its footprint is the union of its views' extents,
not their pooled Gaussian, which sits on the part seen most."""

from __future__ import annotations

import numpy as np
import pytest

from perception.footprint import horizontal_axes, robust_gaussian, union_footprint

UP = np.array([0.0, 0.0, 1.0])
CENTRE = np.array([2.0, 1.0, 0.7])
YAW = np.radians(30.0)
LONG = np.array([np.cos(YAW), np.sin(YAW), 0.0])
SIDE = np.array([-np.sin(YAW), np.cos(YAW), 0.0])
LENGTH, WIDTH = 1.6, 0.8


def _part(a: float, b: float) -> tuple[np.ndarray, np.ndarray]:
    """A view of the table top from ``a`` to ``b`` metres along its long side (whole across it)."""
    R = np.stack([LONG, SIDE, UP], axis=1)
    return CENTRE + (a + b) / 2.0 * LONG, R @ np.diag([(b - a) ** 2 / 12.0, WIDTH**2 / 12.0, 1e-4]) @ R.T


def _views() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ten views of the left end, three of the middle, two of the right end, one of a chair beside it."""
    half = LENGTH / 2.0
    parts = [(-half, -0.2)] * 10 + [(-0.4, 0.4)] * 3 + [(0.3, half)] * 2
    views = [_part(a, b) for a, b in parts]
    views.append((CENTRE + 0.7 * SIDE, np.diag([0.02, 0.02, 0.05])))
    means, covs = (np.stack([v[k] for v in views]) for k in (0, 1))
    return means, covs, np.full(len(views), 100.0)


def test_the_union_of_parts_finds_the_whole_table_where_the_pooled_views_do_not() -> None:
    means, covs, n = _views()
    mean, cov = robust_gaussian(means, covs, n)
    assert abs(LONG @ (mean - CENTRE)) > 0.2  # the part seen most pulls the pooled centre

    new_mean, new_cov = union_footprint(mean, cov, (means, covs, n), UP)
    assert abs(LONG @ (new_mean - CENTRE)) < 0.02
    assert abs(SIDE @ (new_mean - CENTRE)) < 0.04  # the chair's view tilts the axes a little
    length = np.sqrt(12.0 * LONG @ new_cov @ LONG)
    width = np.sqrt(12.0 * SIDE @ new_cov @ SIDE)
    assert length == pytest.approx(LENGTH, abs=0.05)
    assert width == pytest.approx(WIDTH, abs=0.1)  # the chair's view (0.7 m beside it) is left out


def test_the_extent_along_up_stays() -> None:
    means, covs, n = _views()
    mean, cov = robust_gaussian(means, covs, n)
    new_mean, new_cov = union_footprint(mean, cov, (means, covs, n), UP)
    assert new_mean[2] == pytest.approx(mean[2])
    assert new_cov[2, 2] == pytest.approx(cov[2, 2])
    assert np.allclose(new_cov[:2, 2], 0.0)


def test_horizontal_axes_lie_across_up_widest_first() -> None:
    up = np.array([0.1, -0.2, 0.97])
    up /= np.linalg.norm(up)
    cov = np.diag([0.3, 0.01, 0.05])
    axes = horizontal_axes(cov, up)
    assert np.allclose(axes @ up, 0.0, atol=1e-12)
    assert np.allclose(axes @ axes.T, np.eye(2), atol=1e-12)
    spread = [a @ cov @ a for a in axes]
    assert spread[0] > spread[1]
    assert abs(axes[0][0]) > 0.95
