"""``objslam bench longrun`` on a tiny run: its rows are sane and its replayed scene's odometry is continuous."""

from __future__ import annotations

import numpy as np
import pytest

from bench.longrun import HEADER, Looped, measure
from sources import open_dataset

TINY = "synthetic:room?seed=0&frames=40&revolutions=1&width=96&height=72&fps=10"


def test_looped_scene_continues_its_odometry_across_the_wrap_by_the_true_motion():
    data = open_dataset(TINY + "&odom_drift=0")
    looped = Looped(data)
    n, truth = len(data), data.ground_truth.poses
    before, after = looped.frame(n - 1), looped.frame(n)
    step = np.linalg.inv(before.odometry) @ after.odometry
    np.testing.assert_allclose(step, np.linalg.inv(truth[-1]) @ truth[0], atol=1e-9)
    assert after.seq == n and after.timestamp == pytest.approx(n / data.fps)
    np.testing.assert_array_equal(after.rgb, data.frame(0).rgb)


def test_a_tiny_run_reaches_its_rows_and_its_restart_restores_the_live_trajectory():
    rows, summary = measure(TINY, 60, [30, 60, 90])
    assert summary["keyframes"] == 60 and summary["frames"] > 40  # the 40-frame scene was replayed
    assert [row[0] for row in rows] == [30, 60]
    for row in rows:
        values = dict(zip(HEADER, row, strict=True))
        assert values["frames"] >= values["keyframes"]
        assert values["restored = live"] is True
        assert values["store MB"] > 0 and values["kB written / checkpoint p50"] > 0
        assert 0 < values["checkpoints / kf"] <= 1 and values["writer ms p50 / p99"]
        assert 0 < values["checkpoint ms p50"] <= values["p99"] <= values["max"]
        assert 0 < values["checkpoint CPU ms p50"] < values["max"]
        assert values["control CPU ms p50"] > 0
        ratio = values["checkpoint CPU ms p50"] / values["control CPU ms p50"]
        assert values["checkpoint / control"] == pytest.approx(ratio, rel=0.05)  # of rounded figures
        assert 0 < values["restart s"] < 30 and values["RSS MB"] > 0
    growth = [dict(zip(HEADER, row, strict=True))["RSS kB / kf since row 1"] for row in rows]
    assert growth[0] == "" and isinstance(growth[1], float)  # measured from the first row on
