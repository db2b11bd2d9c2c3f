"""The service node's query replies: ``status``, ``trajectory``, ``objects`` and ``loops`` (docs/protocol.md).

A base class of ``service.node.ServiceNode``: each reply is built from the node's immutable summary and counters,
never waiting for the frame being processed, and served from a per-version cache (``service.replies``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Hashable
from typing import TYPE_CHECKING, Any

from graph.geometry import pose_to_tum
from service.config import IngestSettings
from service.protocol import VERSION
from service.replies import Replies

if TYPE_CHECKING:
    from graph.trajectory import Trajectory
    from service.config import Settings
    from service.ingest import IngestQueue
    from service.intake import Intake
    from service.labels import LabelVocabulary
    from service.map_persistence import Persistence
    from service.map_summary import MapSummary
    from service.save_requests import SaveRequests
    from service.stats import ServiceStats
    from slam.core import SlamCore


class NodeQueries:
    """The replies of a ``ServiceNode`` (its base class)."""

    settings: Settings
    stats: ServiceStats
    queue: IngestQueue
    intake: Intake
    labels: LabelVocabulary
    persistence: Persistence | None
    saves: SaveRequests
    replies: Replies
    core: SlamCore
    service_id: str
    prefix: str
    status_sections: dict[str, Callable[[], Any]]
    _started: float
    _summary_version: int

    @property
    def summary(self) -> MapSummary:
        raise NotImplementedError

    @property
    def completed(self) -> int:
        raise NotImplementedError

    def trajectories(self) -> tuple[Trajectory, Trajectory]:
        raise NotImplementedError

    def _replies(self, limits: IngestSettings) -> Replies:
        """The queryables' replies, each recomputed once per change of what it shows (``service.replies``)."""
        entries: dict[str, tuple[Callable[[], dict[str, Any]], Callable[[], Hashable]]] = {
            "status": (self.status, lambda: (self._summary_version, self.stats.received, self.completed)),
            "trajectory": (self.trajectory_reply, lambda: self._summary_version),
            "objects": (self.objects_reply, lambda: self.summary.objects_key),
            "loops": (self.loops_reply, lambda: self.summary.loops_key),
        }
        return Replies(self.prefix, self.service_id, entries, limits.max_queries_per_s)

    def status(self) -> dict[str, Any]:
        """The ``status`` reply (schema in docs/protocol.md), without waiting for the frame being processed."""
        snap = self.stats.snapshot()
        snap.update(self.summary.counts)
        snap.update(
            robot=self.settings.robot,
            protocol_version=VERSION,
            frames_dropped=self.queue.dropped,
            frames_dropped_by_reason=self.intake.dropped_by_reason(),
            queue_depth=self.queue.depth,
            queue_capacity=self.queue.capacity,
            uptime_s=round(time.time() - self._started, 3),
            persistence=self.persistence.status(self.core) if self.persistence is not None else None,
            service_id=self.service_id,
            labels=self.labels.counters(),
            refused={"queries_busy": self.replies.budget.refused, "saves_busy": self.saves.busy},
        )
        snap.update({name: section() for name, section in self.status_sections.items()})  # e.g. ``ros2``
        return snap

    def trajectory_reply(self) -> dict[str, Any]:
        """Optimised poses of every processed frame: ``{"frame": "world", "poses": [[t, tx..qw], ...]}``."""
        traj, _ = self.trajectories()
        rows = [[float(t), *map(float, pose_to_tum(T))] for t, T in zip(traj.timestamps, traj.poses, strict=True)]
        return {"robot": self.settings.robot, "format": "t tx ty tz qx qy qz qw", "poses": rows}

    def objects_reply(self) -> dict[str, Any]:
        """Objects as ellipsoids (SPEC section 4 fields), as of the last processed frame."""
        return {"robot": self.settings.robot, "objects": self.summary.objects}

    def loops_reply(self) -> dict[str, Any]:
        """Every loop-closure candidate with its verdict (SPEC section 4 fields), as of the last processed frame."""
        return {"robot": self.settings.robot, "loops": self.summary.loops}
