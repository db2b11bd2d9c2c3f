"""The map as the SLAM core's readers see it: trajectories, objects, map points and loop records.

Read-only views of ``slam.core.SlamCore``'s state, computed on demand (a status query or an output file), never
during a frame's step.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence

import numpy as np

from graph.object_landmarks import ObjectLandmarks
from graph.trajectory import Trajectory
from graph.window import WindowedGraph
from loops.archive import ColdLog
from loops.closer import LoopCloser
from loops.records import LoopRecord
from perception.object_map import ObjectMapper, object_json
from slam.records import FrameRecord
from slam.segments import Segments


def anchored_frames(records: Sequence[FrameRecord], kf_stamps: Sequence[float]) -> list[tuple[int, np.ndarray]]:
    """Each frame's keyframe and pose in it. Live, a keyframe is made beside the tracking: its frame and the frames
    tracked until it joined the graph were posed against the keyframe before it, and their records say so. Here
    they are tied to the keyframe made from that frame (``kf_stamps``) instead, by their odometry relative to its
    frame's, so that they follow its estimate, not the older keyframe's (7-Scenes live, in one process: ATE
    4.33 -> 4.25 cm, 4.45 -> 4.37 in a second run)."""
    keyframe_of = {t: k for k, t in enumerate(kf_stamps)}
    anchors: list[tuple[int, np.ndarray]] = []
    later: tuple[int, np.ndarray] | None = None  # a keyframe made from a frame posed against an older one
    for r in records:
        k = keyframe_of.get(r.timestamp)
        if k is not None and k > r.keyframe:
            later = (k, r.odometry)
        if later is not None and later[0] > r.keyframe:
            anchors.append((later[0], np.linalg.inv(later[1]) @ r.odometry))
        else:
            later = None
            anchors.append((r.keyframe, r.from_keyframe))
    return anchors


class MapViews:
    """The read side of ``SlamCore`` (its base class): what the core's state means as a map."""

    graph: WindowedGraph
    records: list[FrameRecord]
    kf_stamps: list[float]
    kf_points: ColdLog[np.ndarray]
    objects: ObjectMapper | None
    objects_view: list
    objects_unconfirmed: int = 0  # objects the last applied mapping did not show (``perception.existence``)
    landmarks: ObjectLandmarks | None
    segments: Segments
    methods: Counter[str]

    @property
    def loops(self) -> LoopCloser | None:
        raise NotImplementedError

    def cloud(self) -> np.ndarray:
        """Sparse map points (N, 3) in the trajectory frame: every keyframe's samples at its current estimate."""
        if not self.kf_points:
            return np.zeros((0, 3), np.float32)
        poses = self.graph.poses()
        parts = [
            pts @ poses[k][:3, :3].T.astype(np.float32) + poses[k][:3, 3].astype(np.float32)
            for k, pts in enumerate(self.kf_points[: len(poses)])
        ]
        return np.concatenate(parts)

    def object_list(self) -> list[dict]:
        """Current objects in the frame of the trajectory (``objects.json`` entries)."""
        if self.objects is None:
            return []
        landmarks = self.landmarks.positions() if self.landmarks is not None else {}
        return [object_json(o, landmarks.get(o.id)) for o in self.objects_view]

    def trajectory(self, tied_only: bool = False) -> Trajectory:
        """Optimised poses of every processed frame (keyframe estimate composed with its offset, the keyframe as
        ``anchored_frames`` ties it); with ``tied_only`` only those of frames tied to the map."""
        anchors = anchored_frames(self.records, self.kf_stamps)
        rows = [
            (r.timestamp, k, T)
            for r, (k, T) in zip(self.records, anchors, strict=True)
            if not tied_only or (r.posed and self.segments.tied(k))
        ]
        if not rows:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        kf_poses = self.graph.poses()
        return Trajectory(np.array([t for t, _, _ in rows]), np.stack([kf_poses[k] @ T for _, k, T in rows]))

    def untied_frames(self) -> list[FrameRecord]:
        """The frames whose keyframe's map segment (as ``anchored_frames`` ties it) is not joined to the map (yet):
        those ``trajectory(tied_only=True)`` leaves out."""
        if not self.segments.unjoined() and self.methods["lost"] == 0:
            return []
        anchors = anchored_frames(self.records, self.kf_stamps)
        return [r for r, (k, _) in zip(self.records, anchors, strict=True) if not (r.posed and self.segments.tied(k))]

    def odometry_trajectory(self) -> Trajectory:
        """The front-end (odometry) poses of every processed frame it posed."""
        records = [r for r in self.records if r.posed]
        if not records:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        return Trajectory(np.array([r.timestamp for r in records]), np.stack([r.odometry for r in records]))

    def loop_records(self) -> list[LoopRecord]:
        """Every loop-closure candidate judged so far, oldest first."""
        return list(self.loops.records) if self.loops is not None else []
