"""``serve --ros2``: the ROS 2 ingest and results wired to a service node."""

from __future__ import annotations

from typing import Any

import zenoh

from service.node import ServiceNode
from service.ros2_ingest import Ros2Ingest
from service.ros2_results import Ros2Results


class Ros2Bridge:
    """ROS 2 topics in (``Ros2Ingest``), the map out as ROS 2 messages (``Ros2Results``), ``status.ros2``."""

    def __init__(self, node: ServiceNode):
        settings = node.settings.ros2
        self.node = node
        self.ingest = Ros2Ingest(settings, node.limits.max_image_pixels, self._submit, self._reject)
        self.results = Ros2Results(settings, node) if settings.publish else None
        node.status_sections["ros2"] = self.status

    def _submit(self, payload: bytes) -> None:
        """A paired frame, as a protocol-v1 message: counted and validated like any other."""
        self.node.stats.count_received()
        self.node.submit(payload)

    def _reject(self, reason: str) -> None:
        """A ROS 2 message that could not be read: a received frame, rejected with ``reason``."""
        self.node.stats.count_received()
        self.node.stats.count_rejected(reason)

    def start(self, session: zenoh.Session) -> None:
        self.ingest.start(session)
        if self.results is not None:
            self.results.start(session)

    def stop(self) -> None:
        self.ingest.stop()
        if self.results is not None:
            self.results.stop()

    def status(self) -> dict[str, Any]:
        out = self.ingest.status()
        if self.results is not None:
            out["results"] = self.results.status()
        return out
