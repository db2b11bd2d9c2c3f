"""The keyframe rules of ``objslam bench live-spread`` and the environment that hands them to ``serve``."""

from __future__ import annotations

import numpy as np
import pytest

from bench.live_spread import env_of, median_interval, rules, spread_rows
from perception.keyframing import KeyframeSettings
from service.config import Settings


def test_rules_move_one_threshold_at_a_time_by_the_step() -> None:
    base = KeyframeSettings()
    moved = rules(0.2)
    assert moved["the service's rule"] == base
    assert len(moved) == 5
    for name, rule in moved.items():
        changed = {k for k, v in rule.model_dump().items() if v != getattr(base, k)}
        assert len(changed) == (0 if rule == base else 1), name
        for k in changed:
            assert getattr(rule, k) == pytest.approx(getattr(base, k) * 0.8) or getattr(rule, k) == pytest.approx(
                getattr(base, k) * 1.2
            )


@pytest.mark.parametrize("name", list(rules()))
def test_the_environment_gives_serve_the_rule(name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    rule = rules()[name]
    for key, value in env_of(rule).items():
        monkeypatch.setenv(key, value)
    assert Settings().keyframes == rule


def test_the_summary_row_takes_the_medians_and_counts_the_rules_live_did_no_worse() -> None:
    results = [
        {
            "rule": "a",
            "offline": 0.040,
            "live_end": 0.045,
            "live_settled": 0.041,
            "keyframes": (130, 127),
            "loops": (9, None),
            "offline_published": 0.042,
        },
        {"rule": "b", "offline": 0.038, "live_end": 0.040, "live_settled": 0.036, "offline_published": 0.033},
        {"rule": "c", "offline": 0.042, "live_end": 0.041, "live_settled": 0.039},
    ]
    rows = spread_rows("d", results)
    assert len(rows) == 5
    summary = rows[-2]
    assert "live settled <= offline in 2" in summary[1]
    assert summary[2] == "**4.00**" and summary[4] == "**3.90**"
    assert summary[5] == "-0.10"
    assert rows[-1][5] == "**-0.20**"  # the paired differences +0.10, -0.20, -0.30
    assert "interval -0.30 to 0.10" in rows[-1][1]
    assert rows[0][6:8] == ["130 / 127", "9 / -"] and rows[1][6:8] == ["- / -", "- / -"]
    # against the offline run on the published frames (none for rule c): -0.10 and +0.30
    assert rows[0][8:] == ["4.20", "-0.10"] and rows[2][8:] == ["-", "-"]
    assert "on the published frames in 1" in summary[1] and summary[8] == "**3.75**"
    assert rows[-1][9] == "**0.10**" and "on the published frames -0.10 to 0.30" in rows[-1][1]


def test_the_bootstrap_interval_of_the_median_holds_it_and_narrows_with_more_values() -> None:
    rng = np.random.default_rng(1)
    few, many = rng.normal(0.1, 0.3, 9), rng.normal(0.1, 0.3, 400)
    lo, hi = median_interval(list(few))
    assert lo <= float(np.median(few)) <= hi
    lo2, hi2 = median_interval(list(many))
    assert hi2 - lo2 < (hi - lo) / 3 and lo2 < 0.1 < hi2


def test_several_steps_share_the_service_rule_once() -> None:
    moved = rules(0.05, 0.1, 0.2)
    assert len(moved) == 13
    assert len(set(map(str, moved.values()))) == 13
