"""The odometry source, chosen per frame: a frame's own odometry when it can be chained, else visual odometry.

A robot's odometry and the RGB-D visual front end give poses in different frames, so they can only be mixed by
chaining increments. A frame that carries odometry is posed by its odometry increment since the previous frame
when that frame carried odometry too (``pose = offset @ odometry``, ``offset`` fixed when the chain started).
A frame without odometry, or the first frame with odometry after visual ones, goes to the visual front end,
which follows the odometry frames (it takes each of their keyframes as its own, so it can take over at once;
built only when a frame needed it, the first visual frame restarts tracking as a lost keyframe at the last
pose, which the core relocalizes or starts a map segment with). So one frame
that carries odometry in a visual stream changes nothing, and a stream whose odometry drops out for a few
frames keeps being tracked (before, the first frame decided the source for good, and one crafted frame made
every later frame of a visual robot ``no_odometry``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import numpy as np

from graph.geometry import inverse
from perception.external_odometry import ExternalOdometry
from perception.frame import Frame, FrameRejected, Reason
from perception.frontend import VisualOdometry
from perception.keyframe_deferral import DeferredKeyframes
from perception.keyframing import KeyframeSettings, Step
from perception.odometry import OdometrySettings

Source = Literal["odometry", "visual"]


class PerFrameOdometry:
    """Poses each frame from its own odometry (chained) or by visual odometry (built on first use).

    ``visual`` builds the visual front end; None: frames without odometry are rejected as ``no_odometry``.
    """

    def __init__(self, policy: KeyframeSettings, visual: Callable[[], VisualOdometry] | None):
        self.policy = policy
        self.external = ExternalOdometry(policy)
        self._make_visual = visual
        self.visual: VisualOdometry | None = None
        self._restart = False  # the next frame restarts tracking (``new_session``)
        self.last: Source | None = None  # the source of the last posed frame
        self._offset = np.eye(4)  # map pose = offset @ odometry, while odometry frames follow each other
        self._anchor: np.ndarray | None = None  # the odometry reading of the last frame, when it carried one
        self._last_pose = np.eye(4)
        self._kf_pose: np.ndarray | None = None
        self._since = 0
        self.defer: DeferredKeyframes | None = None  # live: the visual front end's keyframes on another thread

    @property
    def config(self) -> OdometrySettings:
        """The visual front end's settings (relocalization reads them)."""
        return self.visual.config if self.visual is not None else OdometrySettings()

    def chains(self, frame: Frame) -> bool:
        """``frame`` is posed by its odometry increment since the last frame."""
        if frame.odometry is None:
            return False
        return self.last is None or self._anchor is not None

    def check(self, frame: Frame, dt: float) -> None:
        """Reject a frame no source can pose, or whose odometry jumped implausibly since the last frame's."""
        if frame.odometry is None and self._make_visual is None:
            raise FrameRejected(Reason.NO_ODOMETRY, "the frame carries no odometry and visual odometry is off")
        if self.chains(frame) and self._anchor is not None:
            assert frame.odometry is not None
            if self.policy.implausible(self._anchor, frame.odometry, dt):
                raise FrameRejected(Reason.ODOMETRY_JUMP, "odometry jumped implausibly far since the last frame")

    def new_session(self) -> None:
        """The next frame may be anywhere (a new session of the map): it restarts visual tracking as a lost
        keyframe, which the core relocalizes against the stored keyframes (no effect without visual odometry)."""
        self._restart = self.visual is not None or self._make_visual is not None

    def track(self, frame: Frame) -> Step:
        restart, self._restart = self._restart, False
        source: Source = "visual"
        if restart:
            step = self._visual().restart(frame, self._last_pose)
        elif self.chains(frame):
            assert frame.odometry is not None
            if self.last != "odometry":
                self.external.continue_from(self._kf_pose, self._since)
            step = self.external.track_pose(self._offset @ frame.odometry)
            source = "odometry"
            if self.visual is not None:  # ready to take over when the odometry drops out
                self.visual.follow(frame, step.pose, step.keyframe)
        else:
            step = self._visual_step(frame)
        if frame.odometry is not None and step.posed:
            if source == "visual":  # a chain of odometry frames may start here
                self._offset = step.pose @ inverse(frame.odometry)
            self._anchor = frame.odometry
        elif step.posed:
            self._anchor = None
        if step.deferred is not None:
            self.keyframe_taken(step.deferred[1].pose)
        if step.posed:
            self.last, self._last_pose = source, step.pose
            if step.keyframe:
                self._kf_pose, self._since = step.pose, 0
            else:
                self._since += 1
        return step

    def take_deferred(self) -> tuple[Frame, Step] | None:
        """Wait for the keyframe the visual front end is making beside the tracking, and take it (live, when no
        frame comes to hand it on); None when none is being made or it made none."""
        deferral, visual = self.defer, self.visual
        if deferral is None or visual is None or not deferral.pending:
            return None
        deferral.finish(visual, counted=False)
        taken, deferral.finished = deferral.finished, None
        if taken is not None:
            self.keyframe_taken(taken[1].pose)
        return taken

    def keyframe_taken(self, pose: np.ndarray) -> None:
        """A keyframe made beside the tracking (live) became the visual front end's: the chain's keyframe."""
        self._kf_pose, self._since = pose, 0

    def _visual(self) -> VisualOdometry:
        if self.visual is None:
            if self._make_visual is None:
                raise FrameRejected(Reason.NO_ODOMETRY, "the frame carries no odometry and visual odometry is off")
            self.visual = self._make_visual()
        return self.visual

    def _visual_step(self, frame: Frame) -> Step:
        visual = self._visual()
        visual.deferral = self.defer
        if self.last is not None and not visual.started:  # nothing of its own to track from
            return visual.restart(frame, self._last_pose)
        return visual.track(frame)

    def reanchor(self, pose: np.ndarray) -> None:
        """The current keyframe's pose is ``pose`` (relocalization placed it in the map); a chain of the frames'
        own odometry continues from there."""
        if self.visual is not None:
            self.visual.reanchor(pose)
        if self._anchor is not None:
            self._offset = pose @ inverse(self._anchor)
        self._kf_pose = self._last_pose = pose

    @property
    def lost_count(self) -> int:
        return self.visual.lost_count if self.visual is not None else 0

    @property
    def icp_used(self) -> int:
        return self.visual.icp_used if self.visual is not None else 0

    def state(self) -> dict:
        """Plain state of both front ends and the chain."""
        return {
            "external": self.external.state(),
            "visual": None if self.visual is None else self.visual.state(),
            "last": self.last,
            "offset": self._offset,
            "anchor": self._anchor,
            "last_pose": self._last_pose,
            "kf_pose": self._kf_pose,
            "since": self._since,
        }

    def restore(self, state: dict) -> None:
        self.external.restore(state["external"])
        if state["visual"] is not None:
            if self._make_visual is None:
                raise ValueError("the saved map was tracked visually but visual odometry is off")
            self.visual = self._make_visual()
            self.visual.restore(state["visual"])
        self.last, self._offset, self._anchor = state["last"], state["offset"], state["anchor"]
        self._last_pose, self._kf_pose, self._since = state["last_pose"], state["kf_pose"], state["since"]

    def restore_single(self, external: bool, state: dict, last_odometry: np.ndarray | None) -> None:
        """Continue from a snapshot made when the first frame decided the source (``state`` of that front end)."""
        if external:
            self.external.restore(state)
            self.last, self._anchor = "odometry", last_odometry
            self._kf_pose, self._since = state["kf_pose"], state["since"]
            if last_odometry is not None:
                self._last_pose = last_odometry
            return
        if self._make_visual is None:
            raise ValueError("the saved map was tracked visually but visual odometry is off")
        self.visual = self._make_visual()
        self.visual.restore(state)
        self.last = "visual"
        self._kf_pose, self._since = state["kf_pose"], state["since"]
        self._last_pose = state["last_pose"]
