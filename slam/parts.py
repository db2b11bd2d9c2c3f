"""The SLAM core's state in parts a map store can write incrementally (``service.map_store``).

``core_parts`` splits the state that ``slam.snapshot.core_state`` gives into

- **logs**: append-only sequences, handed over live (not copied). Their first ``len`` rows never change while
  the container is the same object: a store writes each row once, when it is new; a container replaced
  (a window roll, a repose, a merge of track runs) is written again whole. Lists, arrays and dicts (rows are
  the dict's items in insertion order).
- **cold** logs among them: large per-keyframe data needed only on demand (the loop-closure features of
  every keyframe, the sparse map points): a store keeps one row per keyframe and need not hold them in RAM.
- **small**: everything else, bounded by the window, the number of objects and the settings, not by the
  length of the run; written whole at each checkpoint.

``assemble`` joins parts (live, or read back from a store) into ``core_state``'s format, which
``slam.snapshot.restore_core`` reads: one definition of the format, whichever way it was stored.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from graph.window_state import joined as graph_joined
from loops.archive import ColdLog
from loops.closer import joined as loops_joined
from perception.object_map import joined as objects_joined
from slam.core import SlamCore
from slam.pose_log import REVISION
from slam.records import FrameRecord

COLD = frozenset({"loops.keyframe_features", "kf_points"})
"""Logs needed only on demand: one row per keyframe in a store, never all in RAM."""


@dataclass
class CoreParts:
    """A core's state as the small part and the append-only logs by dotted name (``COLD`` ones included)."""

    small: dict[str, Any]
    logs: dict[str, Any] = field(default_factory=dict)


def _prefixed(prefix: str, logs: dict[str, Any]) -> dict[str, Any]:
    return {f"{prefix}.{name}": rows for name, rows in logs.items()}


def core_parts(core: SlamCore) -> CoreParts:
    """The parts of ``core``'s state. Waits for the submitted stages (their results are part of the state);
    the logs are the core's own containers: write them before the next step."""
    tracking = core.tracking
    graph_small, graph_logs = core.graph.parts()
    small: dict[str, Any] = {
        "pending_mapping": core.settle(),
        "objects_view": core.objects_view,
        "mapping_errors": core.mapping_errors,
        "camera": tracking.camera if tracking is not None else None,
        "external_odometry": tracking.frontend.last == "odometry" if tracking else False,
        "frontend": tracking.frontend.state() if tracking is not None else None,
        "graph": graph_small,
        "tracking_lost": core.tracking_lost,
        "clock": core.clock.state(),
        "segments": {k: v for k, v in core.segments.state().items() if k != "keyframe_segment"},
        "tracking_state": core.tracking_state.value,
        "methods": dict(core.methods),
        "detections_by_class": dict(core.detections_by_class),
        "objects": None,
        "object_map_version": core.object_map_version,
        "landmarks": None,
        "reposes": core.reposes,
        "loops": None,
        "proposer": None if core.proposer is None else core.proposer.state(),
    }
    logs: dict[str, Any] = {
        "records": core.records,
        "kf_odometry": core.kf_odometry,
        "kf_stamps": core.kf_stamps,
        "kf_points": core.kf_points,
        "keyframe_detections": core.keyframe_detections,
        "object_pose_revisions": core.object_poses.revisions(),
        "segments.keyframe_segment": core.segments.keyframe_segment,
        **_prefixed("graph", graph_logs),
    }
    if core.landmarks is not None:
        small["landmarks"], landmark_logs = core.landmarks.parts()
        logs.update(_prefixed("landmarks", landmark_logs))
    if core.objects is not None:
        small["objects"], object_logs = core.objects.parts()
        logs.update(_prefixed("objects", object_logs))
    if core.loops is not None:
        small["loops"], loop_logs = core.loops.parts()
        logs.update(_prefixed("loops", loop_logs))
    return CoreParts(small, logs)


def _unprefixed(prefix: str, logs: dict[str, Any]) -> dict[str, Any]:
    n = len(prefix) + 1
    return {name[n:]: rows for name, rows in logs.items() if name.startswith(prefix + ".")}


def _poses(rows: Any) -> np.ndarray:
    return np.array(list(rows), float).reshape(-1, 4, 4)


def _columns(r: list[FrameRecord]) -> dict[str, np.ndarray]:
    return {
        "timestamp": np.array([x.timestamp for x in r]),
        "seq": np.array([x.seq for x in r], np.int64),
        "keyframe": np.array([x.keyframe for x in r], np.int64),
        "is_keyframe": np.array([x.is_keyframe for x in r], bool),
        "odometry": _poses(x.odometry for x in r),
        "from_keyframe": _poses(x.from_keyframe for x in r),
        "posed": np.array([x.posed for x in r], bool),
    }


def assemble(parts: CoreParts, materialize: bool = True) -> dict[str, Any]:
    """``core_state``'s format of ``parts`` (logs live or read back: lists, arrays or dicts). ``materialize``:
    plain data throughout, the cold logs read whole; else they stay ``ColdLog``s, read on demand, and the frame
    and factor records stay the records they are (``restore_core`` takes either form), not turned into columns
    only to be turned back."""
    small, logs = parts.small, parts.logs
    r = list(logs["records"])
    state = {
        **small,
        "graph": graph_joined(small["graph"], _unprefixed("graph", logs), records=not materialize),
        "records": _columns(r) if materialize else r,
        "kf_odometry": _poses(logs["kf_odometry"]),
        "kf_stamps": np.array(list(logs.get("kf_stamps", [])), float),  # stored since 2026-12-03
        "kf_points": list(logs["kf_points"]) if materialize else ColdLog.of(logs["kf_points"]),
        "segments": {**small["segments"], "keyframe_segment": list(logs["segments.keyframe_segment"])},
        "keyframe_detections": dict(logs["keyframe_detections"]),
    }
    if "object_pose_revisions" in logs:  # stored since 2026-12-04 (before: the poses, written whole)
        state["object_pose_revisions"] = np.asarray(logs["object_pose_revisions"], float).reshape(-1, REVISION)
    else:
        state["object_poses"] = _poses(logs["object_poses"])
    if small["objects"] is not None:
        state["objects"] = objects_joined(small["objects"], _unprefixed("objects", logs))
    if small["landmarks"] is not None:
        journal = logs.get("landmarks.journal")  # stored since 2026-12-04 (before: ``assigned`` in the small part)
        state["landmarks"] = {
            **small["landmarks"],
            "measurements": dict(logs["landmarks.measurements"]),
            "journal": None if journal is None else np.asarray(journal, np.int64).reshape(-1, 4),
        }
    if small["loops"] is not None:
        state["loops"] = loops_joined(small["loops"], _unprefixed("loops", logs), materialize)
    return state
