"""The pipeline: front-end choice, keyframes, temporal checks, and detections on keyframes."""

from __future__ import annotations

import numpy as np
import pytest

from perception.frame import FrameRejected, Reason
from service.config import load_settings
from service.scheduler import ThreadedRunner
from slam.build import build_core
from sources import open_dataset
from tests.conftest import REDKITCHEN, make_frame, requires_redkitchen


def test_stream_with_odometry_reproduces_it_and_rejects_bad_timestamps():
    p = build_core(load_settings(None, {"loops": {"source": "off"}, "odometry": {"visual": False}}))
    for i in range(20):
        p.step(make_frame(t=1.0 + i, seq=i))
    traj = p.trajectory()
    np.testing.assert_allclose(traj.poses[:, 0, 3], 0.1 * (1.0 + np.arange(20)), atol=1e-9)
    for t, reason in ((20.0, Reason.DUPLICATE_TIMESTAMP), (3.0, Reason.OUT_OF_ORDER)):
        with pytest.raises(FrameRejected) as info:
            p.step(make_frame(t=t))
        assert info.value.reason is reason
    missing = make_frame(t=30.0)
    missing.odometry = None
    with pytest.raises(FrameRejected) as info:
        p.step(missing)
    assert info.value.reason is Reason.NO_ODOMETRY
    empty = make_frame(t=31.0)
    empty.depth[:] = 0
    with pytest.raises(FrameRejected) as info:
        p.step(empty)
    assert info.value.reason is Reason.EMPTY_DEPTH
    assert len(p.records) == 20


def test_provided_detections_bypass_the_detector():
    p = build_core(load_settings(None, {"loops": {"source": "off"}}))
    p.step(make_frame(t=1.0))
    assert p.detections_by_class == {}  # the keyframe's objects are mapped until the next keyframe or flush
    p.flush()
    assert not p.detector_loaded and p.detections_by_class == {"cup": 1}


@requires_redkitchen
def test_keyframes_without_detections_run_the_onnx_detector():
    ds = open_dataset(str(REDKITCHEN))
    p = build_core(load_settings(None, {"loops": {"source": "off"}}))
    p.step(ds.frame(0))
    p.flush()
    assert p.detector_loaded and "detector" in p.timings
    assert {"chair", "cup"} & set(p.detections_by_class)


def test_objects_are_mapped_near_their_true_boxes_with_the_right_labels():
    ds = open_dataset("synthetic:room?seed=1&frames=300")
    p = build_core(load_settings(None, {"loops": {"source": "off"}}))
    for i in range(0, 120):
        p.step(ds.frame(i))
    p.finish()
    objects = p.object_list()
    truth = ds.objects
    assert len(objects) >= 5
    for o in objects:  # every mapped object lies near a true object of its class
        same = [t for t in truth if t.label == o["label"]]
        assert same and min(np.linalg.norm(np.asarray(t.center) - o["mean"]) for t in same) < 0.5
        assert np.asarray(o["cov"]).shape == (3, 3) and np.asarray(o["axes"]).shape == (3, 3)


def test_object_mapping_in_background_gives_exactly_the_inline_result():
    # small frames keep tracking fast, so the mapping thread is still busy when the next keyframes arrive
    ds = open_dataset("synthetic:room?seed=0&frames=160&fps=10&width=320&height=240")
    settings = load_settings(None, {"loops": {"source": "appearance"}})
    inline, background = build_core(settings), build_core(settings, ThreadedRunner())
    try:
        frames = [ds.frame(i) for i in range(160)]
        for p in (background, inline):  # one after the other: the worker runs ahead of the mapping thread
            for frame in frames:
                p.step(frame)
        for p in (inline, background):
            p.finish()
        assert background.graph.num_landmarks > 0 and len(background.object_list()) >= 5
        assert np.array_equal(inline.trajectory().poses, background.trajectory().poses)
        assert inline.object_list() == background.object_list()
        assert inline.keyframe_detections.keys() == background.keyframe_detections.keys()
    finally:
        background.close()


@requires_redkitchen
def test_detection_on_its_own_thread_gives_exactly_the_inline_result():
    ds = open_dataset(str(REDKITCHEN))
    settings = load_settings(None, {"loops": {"source": "off"}})
    inline, background = build_core(settings), build_core(settings, ThreadedRunner())
    try:
        frames = [ds.frame(i) for i in range(0, 120, 2)]
        for p in (background, inline):
            for frame in frames:
                p.step(frame)
            p.finish()
        assert isinstance(background.runner, ThreadedRunner)  # detection ran on the scheduler's detector thread
        assert len(background.keyframe_detections) >= 8 and sum(background.detections_by_class.values()) >= 8
        assert background.keyframe_detections == inline.keyframe_detections
        assert background.object_list() == inline.object_list()
        assert np.array_equal(inline.trajectory().poses, background.trajectory().poses)
    finally:
        background.close()


def test_a_failing_object_mapping_is_counted_and_the_pipeline_goes_on(monkeypatch):
    p = build_core(load_settings(None, {"loops": {"source": "off"}}), ThreadedRunner())
    try:

        def broken(*args):
            raise ValueError("a box the mapper cannot handle")

        monkeypatch.setattr(p.objects, "add_keyframe", broken)
        for i in range(10):
            p.step(make_frame(t=1.0 + i, seq=i))
        p.flush()
        assert p.mapping_errors == p.graph.num_keyframes >= 2
        assert len(p.records) == 10 and p.object_list() == []
        monkeypatch.undo()
        p.step(make_frame(t=20.0, seq=20))
        p.step(make_frame(t=30.0, seq=30))
        p.flush()
        assert p.mapping_errors == p.graph.num_keyframes - 2 and p.keyframe_detections
    finally:
        p.close()


def test_each_step_returns_what_it_changed():
    ds = open_dataset("synthetic:room?seed=0&frames=160&fps=10&width=320&height=240")
    core = build_core(load_settings(None, {"loops": {"source": "appearance"}}))
    results = [core.step(ds.frame(i)) for i in range(160)]
    assert [r.record for r in results] == core.records
    assert all((r.keyframe is not None) == r.record.is_keyframe for r in results)
    assert [r.keyframe for r in results if r.keyframe is not None] == list(range(core.graph.num_keyframes))
    judged = [record for r in results for record in r.loops]
    assert judged == core.loop_records() and any(record.accepted for record in judged)
    assert sum(r.objects_changed for r in results) >= 1 and all("frontend" in r.timings for r in results)
