"""``objslam bench sessions`` on one held-out map and one start: the measurement is what the table says."""

from __future__ import annotations

import math
from dataclasses import replace

from bench.sessions import FALSE_M, MAPS, SESSION_FRAMES, measure


def test_a_second_session_is_measured_localized_truthfully_and_in_the_maps_frame():
    (start,) = measure((replace(MAPS[0], starts=1),))
    assert start.reached == 1  # a lap on: every place is mapped
    assert start.localized_after is not None and 1 <= start.localized_after <= SESSION_FRAMES
    assert start.against is not None and not start.false
    assert math.isfinite(start.ate_m) and start.ate_m < FALSE_M  # in the map's frame, not its own
    assert 0 < start.map_ate_m < 0.1
