"""The map as ROS 2 messages on rmw_zenoh keys, for ROS 2 nodes, RViz2 and Foxglove.

``<namespace>/path`` (``nav_msgs/msg/Path``: the optimised keyframe poses, republished when the graph moves),
``<namespace>/pose`` (``geometry_msgs/msg/PoseStamped``: the newest frame) and ``<namespace>/objects``
(``visualization_msgs/msg/MarkerArray``: labelled ellipsoids coloured by class, accepted loop closures as lines),
all in the ``ros2.map_frame`` frame, with the type hashes of ROS 2 Jazzy and rmw_zenoh's attachment (sequence
number, source time, publisher gid). Liveliness tokens announce the node and its publishers the way rmw_zenoh
does, so ``ros2 topic list`` on the same router can see them. A thread of its own polls the node's summary a
few times a second (the path and the objects at most twice): publishing never delays a frame.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from typing import Any

import numpy as np
import zenoh

from service.ros2_settings import Ros2Settings
from sources.ros2 import keys, messages

log = logging.getLogger(__name__)

PERIOD_S = 0.2
MAP_PERIOD_S = 0.5
"""The path and the objects are published at most this often: serialising them costs the worker's GIL time."""
NODE_NAME = "objslam"
QOS = "::,10:,:,:,,"
"""rmw_zenoh's QoS field of a liveliness token (defaults: reliable, volatile, keep last 10), best effort here."""


class Ros2Results:
    """Publishes the path, the newest pose and the objects of ``node`` (a ServiceNode) as ROS 2 messages."""

    def __init__(self, settings: Ros2Settings, node: Any):
        self.settings, self.node = settings, node
        self.published: dict[str, int] = {"path": 0, "pose": 0, "objects": 0}
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._tokens: list[Any] = []
        self._gids: dict[str, bytes] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="objslam-ros2-results", daemon=True)
        self._seen: dict[str, Any] = {}  # the version of each message last published
        self._sent_at: dict[str, float] = {}  # and when (monotonic)
        self._kf_times: list[float] = []  # the keyframes' times, from the records read so far

    def key(self, name: str) -> str:
        typename = {"path": messages.PATH, "pose": messages.POSE_STAMPED, "objects": messages.MARKER_ARRAY}[name]
        return keys.ros_key(self.settings.domain_id, self.topic(name), typename, keys.type_hash(typename))

    def topic(self, name: str) -> str:
        return f"{self.settings.results_namespace.rstrip('/')}/{name}"

    def start(self, session: zenoh.Session) -> None:
        zid = str(session.zid())
        domain = self.settings.domain_id
        self._tokens.append(session.liveliness().declare_token(f"@ros2_lv/{domain}/{zid}/0/0/NN/%/%/{NODE_NAME}"))
        for entity, (name, typename) in enumerate(
            (("path", messages.PATH), ("pose", messages.POSE_STAMPED), ("objects", messages.MARKER_ARRAY)), start=1
        ):
            self._publishers[name] = session.declare_publisher(self.key(name))
            self._gids[name] = os.urandom(16)
            dds = keys.dds_type_name(typename)
            topic = self.topic(name).replace("/", "%")
            token = (
                f"@ros2_lv/{domain}/{zid}/0/{entity}/MP/%/%/{NODE_NAME}/{topic}/{dds}/{keys.type_hash(typename)}/{QOS}"
            )
            self._tokens.append(session.liveliness().declare_token(token))
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        for entity in [*self._publishers.values(), *self._tokens]:
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()
        self._publishers.clear()
        self._tokens.clear()

    def _run(self) -> None:
        while not self._stop.wait(PERIOD_S):
            try:
                self.publish_changes()
            except Exception:  # publishing must never take the service down
                log.exception("could not publish the ROS 2 results")

    def publish_changes(self) -> None:
        """Publish what changed since the last call: the pose per frame, the path when the graph moved and the
        objects when they changed, those two at most every ``MAP_PERIOD_S`` (their cost grows with the map).

        The core's lock (which the worker needs for every frame) is held only to read what changed: nothing
        when no frame came, the keyframe times of the new records only."""
        node, frame_id, now = self.node, self.settings.map_frame, time.monotonic()
        summary = node.summary
        with node.hold_core():
            core = node.core
            if not core.records:
                return
            versions = {
                "pose": len(core.records),
                "path": (core.graph.updates, core.graph.num_keyframes),
                "objects": (summary.objects_key, summary.loops_key),
            }
            changed = [name for name, version in versions.items() if self._due(name, version, now)]
            if not changed:
                return
            kf_poses = core.graph.poses()
            last = core.records[-1]
            pose = kf_poses[last.keyframe] @ last.from_keyframe
            self._kf_times += core.kf_stamps[len(self._kf_times) :]
        stamp = last.timestamp
        if "pose" in changed:
            self._put("pose", messages.encode_pose_stamped(stamp, frame_id, pose), stamp)
        if "path" in changed:
            n = min(len(self._kf_times), len(kf_poses))
            path = list(zip(self._kf_times[:n], kf_poses[:n], strict=True))
            self._put("path", messages.encode_path(stamp, frame_id, path), stamp)
        if "objects" in changed:
            loops = _segments(summary.loops, kf_poses)
            self._put("objects", messages.encode_marker_array(stamp, frame_id, summary.objects, loops), stamp)
        for name in changed:
            self._seen[name], self._sent_at[name] = versions[name], now

    def _due(self, name: str, version: Any, now: float) -> bool:
        """``name`` changed since it was last published, and (path, objects) that was ``MAP_PERIOD_S`` ago."""
        if self._seen.get(name) == version:
            return False
        return name == "pose" or now - self._sent_at.get(name, -np.inf) >= MAP_PERIOD_S

    def _put(self, name: str, payload: bytes, stamp: float) -> None:
        self.published[name] += 1
        attachment = keys.encode_attachment(
            keys.Attachment(self.published[name], time.time_ns(), self._gids.get(name, bytes(16)))
        )
        self._publishers[name].put(payload, attachment=attachment)

    def status(self) -> dict[str, Any]:
        return {"published": dict(self.published), "keys": {name: self.key(name) for name in self.published}}


def _segments(records: list[dict[str, Any]], kf_poses: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The accepted loop closures as (position, position) of their two keyframes."""
    out = []
    for r in records:
        a, b = r.get("query_keyframe"), r.get("match_keyframe")
        if r.get("accepted") and isinstance(a, int) and isinstance(b, int) and max(a, b) < len(kf_poses):
            out.append((kf_poses[a][:3, 3], kf_poses[b][:3, 3]))
    return out
