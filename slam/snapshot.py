"""The SLAM core's whole state as plain data, and a core rebuilt from it (``service.persistence`` writes it).

Plain data: numbers, arrays, objslam's own dataclasses. cv2, gtsam and ONNX objects are rebuilt, never
saved: the graph replays its recorded factors and iSAM2 updates, so a restored core continues bit for bit
like one that never stopped. States written by release 0.1.0 (loop verdicts as tuples of dicts) restore too.
"""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np

from graph.window import WindowedGraph
from loops.archive import ColdLog
from loops.records import LoopRecord, Verified
from slam.build import build_core
from slam.core import SlamCore
from slam.parts import assemble, core_parts
from slam.pose_log import PlacedPoses
from slam.records import FrameRecord, KeyframeLoops
from slam.runner import Done, Handle, Runner
from slam.segments import Segments, TrackingState
from slam.settings import SlamConfig


def core_state(core: SlamCore) -> dict[str, Any]:
    """Everything needed to continue exactly where ``core`` is. Waits for the submitted stages (their results
    are part of the state). The result shares arrays with the core: serialise it before the next step."""
    return assemble(core_parts(core))


def _loop_results(saved: Any) -> KeyframeLoops | None:
    """A pending loop verification as saved (0.1.0: a tuple (verified with dict records, timings))."""
    if saved is None or isinstance(saved, KeyframeLoops):
        return saved
    verified, timings = saved
    return KeyframeLoops(
        [
            Verified(v.record if isinstance(v.record, LoopRecord) else LoopRecord.from_json(v.record), v.relative)
            for v in verified
        ],
        dict(timings),
    )


def restore_core(settings: SlamConfig, state: dict[str, Any], runner: Runner | None = None) -> SlamCore:
    """A core that continues from ``state`` (of ``core_state``) exactly as the saved one would have."""
    graph = WindowedGraph.from_state(state["graph"], settings.graph)
    core = build_core(settings, runner, graph)
    if state["camera"] is not None:
        tracking = core.tracking_factory(state["camera"], state["external_odometry"])
        saved = state["frontend"]
        if "external" in saved:
            tracking.frontend.restore(saved)
        else:  # saved when the first frame decided the source: that front end's own state
            records = state["records"]
            odometry = [x.odometry for x in records[-1:]] if isinstance(records, list) else records["odometry"]
            last = odometry[-1] if len(odometry) else None
            tracking.frontend.restore_single(state["external_odometry"], saved, last)
        if tracking.loops is not None and state["loops"] is not None:
            tracking.loops.restore(state["loops"])
        core.connect(tracking)
        if core.proposer is not None and state.get("proposer") is not None:
            core.proposer.restore(state["proposer"])
    core.records = _records(state["records"])
    core.clock.restore(state.get("clock", {}), core.records[-1].timestamp if core.records else None)
    core.kf_odometry = list(state["kf_odometry"])
    core.kf_stamps = _keyframe_stamps(state, core.records)
    core.kf_points = ColdLog.of(state.get("kf_points", []))
    core.tracking_lost = state["tracking_lost"]
    if "segments" in state:
        core.segments = Segments.from_state(state["segments"])
        core.tracking_state = TrackingState(state["tracking_state"])
        core.methods = Counter(state["methods"])
    else:  # saved before map segments: one segment of every keyframe
        for k in range(len(core.kf_odometry)):
            core.segments.add_keyframe(k)
    core.keyframe_detections = state["keyframe_detections"]
    core.detections_by_class = Counter(state["detections_by_class"])
    if core.objects is not None and state["objects"] is not None:
        core.objects.restore(state["objects"])
    core.object_map_version = state["object_map_version"]
    if core.landmarks is not None and state.get("landmarks") is not None:
        core.landmarks.restore(state["landmarks"])
    if "object_pose_revisions" in state:
        core.object_poses = PlacedPoses(revisions=state["object_pose_revisions"])
    else:  # saved before 2026-12-04 (the poses), or before the poses were saved
        core.object_poses = PlacedPoses(state.get("object_poses", graph.poses()[: len(core.keyframe_detections)]))
    core.reposes = state.get("reposes", 0)
    core.mapping_errors = state.get("mapping_errors", 0)
    if core.objects is not None:
        core.objects_view = list(state.get("objects_view", core.objects.objects))
        core.objects_unconfirmed = len(core.objects.clusterer.unkept)
    for results in state.get("pending_mapping", []):
        jobs: dict[str, Handle] = {"objects": Done(results["objects"])} if "objects" in results else {}
        if "loops" in results:
            jobs["loops"] = Done(_loop_results(results["loops"]))
        core.pending.append(jobs)
    return core


def _records(r: dict[str, np.ndarray] | list[FrameRecord]) -> list[FrameRecord]:
    """The frame records of a state: the records themselves (read back from a map store), or columns."""
    if isinstance(r, list):
        return r
    rows = zip(
        r["timestamp"], r["seq"], r["keyframe"], r["is_keyframe"], r["odometry"], r["from_keyframe"], strict=True
    )
    posed = r.get("posed", np.ones(len(r["timestamp"]), bool))  # saved before unposed frames: all posed
    return [
        FrameRecord(float(t), int(s), int(k), bool(kf), odo, off, bool(p))
        for (t, s, k, kf, odo, off), p in zip(rows, posed, strict=True)
    ]


def _keyframe_stamps(state: dict[str, Any], records: list[FrameRecord]) -> list[float]:
    """The keyframes' timestamps; saved before they were kept, every keyframe's record was its own frame's."""
    stamps = state.get("kf_stamps")
    if stamps is not None and len(stamps) == len(state["kf_odometry"]):
        return [float(t) for t in stamps]
    return [r.timestamp for r in records if r.is_keyframe]
