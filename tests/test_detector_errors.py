"""The simulated detector's errors (sources.detector_errors) and the family bench under them."""

from __future__ import annotations

import io

import numpy as np
import pytest
from rich.console import Console

from bench.box_stability import moved, source_detections, stability
from bench.objects_family_errors import LEVELS, run_error_sweep, scene_result
from perception.camera import Intrinsics
from perception.frame import Detection
from sources.base import DatasetError
from sources.detector_errors import CONFUSED_WITH, PART_KEPT, confused, part_box
from sources.synthetic import parse_synthetic_spec

SPEC = "synthetic:family?seed=2&frames=40&width=160&height=120"


def _detections(spec: str, frames: range) -> list[list[tuple[str, tuple[float, ...]]]]:
    data = parse_synthetic_spec(spec)
    return [[(d.label, tuple(d.box)) for d in data.frame(i).detections or []] for i in frames]


def test_part_box_keeps_a_share_of_one_side() -> None:
    rng = np.random.default_rng(0)
    box = np.array([10.0, 20.0, 110.0, 220.0])
    sides = set()
    for _ in range(200):
        part = part_box(box, rng, 1.0)
        assert box[0] <= part[0] < part[2] <= box[2] and box[1] <= part[1] < part[3] <= box[3]
        kept_w, kept_h = (part[2] - part[0]) / 100.0, (part[3] - part[1]) / 200.0
        assert (kept_w == 1.0) != (kept_h == 1.0)  # one dimension cut, the other whole
        assert PART_KEPT[0] <= min(kept_w, kept_h) <= PART_KEPT[1]
        sides.add((part[0] > box[0], part[1] > box[1], part[2] < box[2], part[3] < box[3]))
    assert len(sides) == 4
    assert part_box(box, rng, 0.0) is box


def test_confused_labels_come_from_the_table() -> None:
    rng = np.random.default_rng(1)
    assert {confused("cup", rng, 1.0) for _ in range(100)} == set(CONFUSED_WITH["cup"])
    assert {confused("cup", rng, 0.0) for _ in range(20)} == {"cup"}
    assert confused("teddy bear", rng, 1.0) == "teddy bear"  # nothing it is mistaken for
    share = np.mean([confused("chair", rng, 0.1) != "chair" for _ in range(4000)])
    assert 0.08 < share < 0.12


def test_default_knobs_leave_the_detections_as_they_were() -> None:
    frames = range(0, 40, 7)
    explicit = _detections(SPEC + "&box_noise=0.025&confusion=0&part_boxes=0", frames)
    assert explicit == _detections(SPEC, frames)
    assert sum(map(len, explicit)) > 10


def test_knobs_change_labels_and_boxes_as_asked() -> None:
    data = parse_synthetic_spec(SPEC + "&confusion=1&box_noise=0")
    exact = parse_synthetic_spec(SPEC + "&box_noise=0")
    truth = {o.id: o.label for o in data.objects}
    checked = 0
    for i in range(0, 40, 5):
        ids = data.detection_instance_ids(i)
        for det, oid, plain in zip(data.frame(i).detections or [], ids, exact.frame(i).detections or [], strict=True):
            if oid == 0:
                continue
            want = CONFUSED_WITH.get(truth[oid], (truth[oid],))
            assert det.label in want and plain.label == truth[oid]
            assert det.box == plain.box  # confusion leaves the box
            checked += 1
    assert checked > 5
    loose = _detections(SPEC + "&box_noise=0.1", range(0, 40, 5))
    tight = _detections(SPEC, range(0, 40, 5))
    assert [[d[0] for d in f] for f in loose] == [[d[0] for d in f] for f in tight] and loose != tight


def test_out_of_range_knobs_are_refused() -> None:
    for bad in ("box_noise=0.5", "confusion=1.5", "part_boxes=-0.1"):
        with pytest.raises(DatasetError, match="out of range"):
            parse_synthetic_spec(SPEC + "&" + bad)


def test_confused_labels_cost_objects_in_the_sweep(tmp_path) -> None:
    clean, mixed = scene_result(2, 40, ""), scene_result(2, 40, "confusion=1.0")
    assert clean["present"] == mixed["present"] > 0
    assert mixed["found"] < clean["found"] and mixed["false"] > clean["false"]
    out = tmp_path / "bench.md"
    summary = run_error_sweep(Console(file=io.StringIO()), [2], 40, out, workers=1)
    text = out.read_text()
    assert "<!-- bench:objects-family-errors -->" in text
    assert all(name in text for name in LEVELS) and set(summary) == set(LEVELS)
    first = summary["the family's detector"]["aggregate"]["mapped"]["median"]
    assert first == pytest.approx(100.0 * clean["found"] / clean["present"])


def test_moved_box_follows_the_camera() -> None:
    K = Intrinsics(500.0, 500.0, 320.0, 240.0)
    depth = np.full((480, 640), 2.0)
    box = (300.0, 200.0, 340.0, 260.0)
    assert moved(box, depth, K, np.eye(4)) == pytest.approx(box)
    T = np.eye(4)
    T[0, 3] = -0.1  # the camera moved 0.1 m right: the scene moves left by fx * 0.1 / 2 = 25 px
    assert moved(box, depth, K, T) == pytest.approx((275.0, 200.0, 315.0, 260.0))
    T = np.eye(4)
    T[2, 3] = -1.0  # 1 m closer: twice the size, its centre twice as far from the principal point
    assert moved(box, depth, K, T) == pytest.approx((280.0, 160.0, 360.0, 280.0))


def test_stability_counts_wobble_parts_and_switches() -> None:
    whole = Detection("chair", 0.9, (100.0, 100.0, 200.0, 300.0))
    wobble = Detection("chair", 0.9, (105.0, 100.0, 200.0, 310.0))
    part = Detection("chair", 0.9, (100.0, 100.0, 200.0, 190.0))
    couch = Detection("couch", 0.9, (101.0, 100.0, 200.0, 300.0))
    s = stability([([wobble], [whole]), ([part], [wobble]), ([couch], [wobble])], 640, 480)
    assert (s.frames, s.pairs) == (3, 2)
    assert s.part_pairs == pytest.approx(0.5)
    assert s.switches == pytest.approx(0.5)  # of the two detections over a previous box, the couch switched
    assert s.p90 > 0.04


def test_simulated_wobble_shows_in_the_box_stability() -> None:
    tight, _, _ = source_detections(SPEC + "&box_noise=0", 0, 30)
    loose, w, h = source_detections(SPEC + "&box_noise=0.08", 0, 30)
    a, b = stability(tight, w, h), stability(loose, w, h)
    assert a.pairs > 20 and b.pairs > 20
    assert b.robust_sd > 2 * a.robust_sd and b.robust_sd > 0.06
