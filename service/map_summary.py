"""What the queryables report of the map: an immutable summary the worker takes between frames, and the
events that the change from one summary to the next publishes."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from slam.core import SlamCore


@dataclass(frozen=True)
class MapSummary:
    """What the queryables report of the map, taken by the worker between frames; never changed afterwards."""

    counts: dict[str, Any] = field(default_factory=dict)  # status fields: keyframes, poses, factors, ...
    objects: list[dict] = field(default_factory=list)
    object_map_version: int = -1
    loops: list[dict] = field(default_factory=list)
    loops_key: tuple[int, int] = (-1, -1)  # (records, accepted) when ``loops`` was copied
    objects_key: tuple[int, int] = (-1, -1)  # (object map version, graph update) when ``objects`` was copied


def summarize(core: SlamCore, old: MapSummary) -> MapSummary:
    """The map's counts, objects and loop records now. Objects and loop records are copied only when they
    changed since ``old``, so a frame that changes neither costs a few attribute reads."""
    graph = core.graph
    # landmark estimates move with every graph update; without landmarks only the object map version counts
    objects_key = (core.object_map_version, graph.updates if graph.num_landmarks else 0)
    objects = old.objects if old.objects_key == objects_key else core.object_list()
    closer = core.loops  # its accepted loops are the records marked accepted: counted without a scan
    n_records, accepted = (len(closer.records), len(closer.accepted)) if closer is not None else (0, 0)
    key = (n_records, accepted)
    loops = old.loops if key == old.loops_key else [r.to_json() for r in core.loop_records()]
    counts = {
        "keyframes": graph.num_keyframes,
        "poses": graph.num_keyframes,
        "factors": graph.num_factors,
        "landmarks": graph.num_landmarks,
        "tracking_lost": core.tracking_lost,
        "tracking": tracking_health(core),
        "landmark_measurements": len(core.landmarks.assigned) if core.landmarks is not None else 0,
        "object_reposes": core.reposes,
        "object_mapping_errors": core.mapping_errors,
        "mapping": {  # keyframe mapping behind tracking (its lag: latency.mapping_lag)
            "live": core.live,
            "pending_keyframes": len(core.pending),
            "detections_skipped": core.detections_skipped,
        },
        "loop_closures": {"accepted": accepted, "rejected": n_records - accepted},
        "graph_window": {"first_keyframe": graph.start, "whole_graph_solves": graph.global_solves},
        "keyframe_detections_by_class": dict(core.detections_by_class),
        "objects": len(objects),
        "objects_by_class": dict(Counter(o["label"] for o in objects)),
        "objects_unconfirmed": core.objects_unconfirmed,  # detected too seldom where they stood in view: not shown
    }
    return MapSummary(counts, objects, core.object_map_version, loops, key, objects_key)


def loop_events(records: list[dict[str, Any]], published: set[int]) -> tuple[list[dict[str, Any]], set[int]]:
    """Events for the loops accepted and retracted since the loops ``published`` (factor indices) were; and
    the factor indices accepted now."""
    accepted = {r["factor"]: r for r in records if r["accepted"]}
    new = [accepted[f] for f in sorted(accepted.keys() - published)]
    gone = [r for r in records if not r["accepted"] and r.get("factor") in published]
    events = [{"type": "loop_closure", "accepted": len(accepted), "latest": new}] if new else []
    if gone:
        events.append({"type": "loop_retracted", "accepted": len(accepted), "retracted": gone})
    return events, set(accepted)


def tracking_health(core: SlamCore) -> dict[str, Any]:
    """The ``tracking`` block of ``status``: the last frame's state, frames per method, map segments started,
    joins and relocalizations, and the frames not tied to the map as ``[first, last]`` seq ranges."""
    segments = core.segments
    return {
        "state": core.tracking_state.value,
        "methods": dict(core.methods),
        "segments": segments.count,
        "segments_unjoined": segments.unjoined(),
        "joins": segments.joins,
        "relocalizations": segments.relocalizations,
        "time_resets": core.clock.resets,
        "untied_frames": seq_ranges([r.seq for r in core.untied_frames()]),
    }


def seq_ranges(seqs: list[int]) -> list[list[int]]:
    """Sorted frame numbers as ``[first, last]`` runs of consecutive ones."""
    out: list[list[int]] = []
    for s in sorted(seqs):
        if out and s == out[-1][1] + 1:
            out[-1][1] = s
        else:
            out.append([s, s])
    return out
