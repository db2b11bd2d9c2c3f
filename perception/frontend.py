"""Odometry front ends: RGB-D visual odometry here, external odometry in ``perception.external_odometry`` (SPEC 6.4).

Both decide keyframes and give, for each keyframe, the relative pose from the previous keyframe with
its noise: the odometry between-factor of the graph.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace

import cv2
import numpy as np

from graph.geometry import inverse, motion_magnitude, relative
from perception.fallback import FallbackChain
from perception.frame import CameraModel, Frame
from perception.hypotheses import Hypothesis, scaled_motion
from perception.icp import IcpTarget, depth_agreement, icp_refine, icp_target
from perception.keyframe_deferral import DeferredKeyframes
from perception.keyframe_tracker import KeyframeTracker
from perception.keyframing import KeyframeSettings, Step
from perception.odometry import (
    FeatureExtractor,
    Features,
    OdometrySettings,
    Rejected,
    RelativePoseEstimator,
    gray_image,
)

log = logging.getLogger(__name__)


class VisualOdometry:
    """Frame-to-keyframe RGB-D odometry: ORB + depth on the keyframe, PnP-RANSAC against the new frame.

    When the features fail, and at a keyframe whose pose the depth does not confirm, a fallback chain (wide
    features, guided matching, depth ICP from a constant-velocity prior) offers more poses, judged by the
    agreement of the two depth images (``perception.icp.depth_agreement``); the step records its method.
    When nothing agrees the frame is lost (``Step.lost``, no factor; the core relocalizes it or starts a
    map segment). It never raises. ``policy`` decides keyframes; ``config`` the rest.
    """

    def __init__(self, camera: CameraModel, policy: KeyframeSettings, config: OdometrySettings | None = None):
        config = config if config is not None else OdometrySettings()
        self.policy, self.config = policy, config
        self.camera = camera
        self.extractor = FeatureExtractor(camera, config)
        self.estimator = RelativePoseEstimator(camera, config)
        self.chain = FallbackChain(camera, config, self.estimator)
        self.tracker = KeyframeTracker(config.flow_points, config.flow_max_fb_px)  # between keyframes (flow)
        self.deferral: DeferredKeyframes | None = None  # live: keyframes made on another thread
        self._targets: dict[int, tuple[np.ndarray, IcpTarget]] = {}  # id(keyframe depth) -> (depth, ICP target)
        self._kf_pose: np.ndarray | None = None
        self._kf_features: Features | None = None
        self._kf_depth: np.ndarray | None = None
        self._kf_gray: np.ndarray | None = None
        self._history: list[tuple[Features, np.ndarray]] = []  # older keyframes, newest last
        self.icp_used = 0
        self._last_pose = np.eye(4)
        self._last_time = 0.0
        self._velocity: tuple[np.ndarray, float] | None = None  # the last posed step (T_prev_last) and its dt
        self._since = 0
        self.lost_count = 0

    _STATE = (
        "_kf_pose",
        "_kf_features",
        "_kf_depth",
        "_kf_gray",
        "_history",
        "icp_used",
        "_last_pose",
        "_last_time",
        "_velocity",
        "_since",
        "lost_count",
    )

    def state(self) -> dict:
        """Plain tracking state: the keyframe's pose, features, depth and image, older keyframes, the motion
        prior, counters.

        The ORB extractor and matcher (cv2 objects) are not state: they are rebuilt from the camera; nor are
        the settings, which come from the configuration (a snapshot holds plain data only).
        """
        return {name.lstrip("_"): getattr(self, name) for name in self._STATE}

    def restore(self, state: dict) -> None:
        defaults = {"kf_gray": None, "last_time": 0.0, "velocity": None}  # saved before the fallback chain
        for name in self._STATE:
            key = name.lstrip("_")
            setattr(self, name, state[key] if key in state else defaults[key])

    def track(self, frame: Frame) -> Step:
        """The frame's step; with ``deferral`` (live) it may carry a keyframe decided earlier (``Step.deferred``)."""
        gray, deferral = gray_image(frame), self.deferral
        if deferral is not None:
            deferral.ready(self)  # a finished keyframe becomes the one tracked against
        step = self._track(frame, gray)  # (or, when the flow fails, waits for the pending one)
        if deferral is not None:
            step.deferred, deferral.finished = deferral.finished, None
            deferral.count(step)
        return step

    def _track(self, frame: Frame, gray: np.ndarray) -> Step:
        kf_pose, kf_features, kf_depth = self._kf_pose, self._kf_features, self._kf_depth
        started = kf_pose is not None and kf_features is not None and kf_depth is not None  # all three or none
        if started:
            self._since += 1
        if started and kf_pose is not None and self.config.tracker == "flow":
            flowed = self._flow(gray, self._prediction(frame.timestamp, kf_pose))
            if flowed is None and self.deferral is not None and self.deferral.pending:  # wait for the keyframe
                self.deferral.finish(self, counted=True)
                assert self._kf_pose is not None
                flowed = self._flow(gray, self._prediction(frame.timestamp, self._kf_pose))
            kf_pose = self._kf_pose
            if flowed is not None and kf_pose is not None and self._flow_poses(frame, gray, flowed):
                step = Step(kf_pose @ flowed.T, False, inliers=flowed.inliers, method="tracked")
                return self._posed(frame, step)  # between keyframes, or a keyframe made on another thread
        depth = frame.depth_m()
        features = self.extractor.extract_gray(gray, depth)
        kf_pose = self._kf_pose
        if kf_pose is None or self._kf_features is None or self._kf_depth is None:  # the first frame
            step = Step(np.eye(4), True, features=features, method="features")
            return self._new_keyframe(np.eye(4), features, depth, frame, step, gray)
        try:
            rel = self.estimator.estimate(self._kf_features, features)
            primary: Hypothesis | None = Hypothesis("features", rel.T_a_b, rel.sigma_m, rel.sigma_deg, rel.inliers)
        except Rejected as exc:
            primary, rejected = None, exc
        if primary is not None and not self._keyframe_due(primary):
            return self._posed(frame, Step(kf_pose @ primary.T, False, inliers=primary.inliers, method="features"))
        step_or_none = self.keyframe_step(frame, features, depth, primary, self._prediction(frame.timestamp, kf_pose))
        if step_or_none is None:
            return self._lost(frame, features, depth, rejected if primary is None else Rejected("no_agreement"))
        return self._new_keyframe(step_or_none.pose, features, depth, frame, self._posed(frame, step_or_none), gray)

    def _flow_poses(self, frame: Frame, gray: np.ndarray, flowed: Hypothesis) -> bool:
        """The flow's pose stands for ``frame``: no keyframe is due, or (live) its keyframe is made elsewhere."""
        if not self._keyframe_due(flowed):
            return True
        if self.deferral is None:
            return False
        self.deferral.take(self, frame, gray, flowed)
        return True

    def keyframe_step(
        self, frame: Frame, features: Features, depth: np.ndarray, primary: Hypothesis | None, prior: np.ndarray
    ) -> Step | None:
        """The keyframe step of ``frame`` (its factor, sigmas and skip edges) from its features and the best pose
        hypothesis; None when no hypothesis agrees with the depth. Reads only the keyframe's state, so it may run
        on another thread while frames are tracked by flow (``perception.keyframe_deferral``)."""
        kf_pose = self._kf_pose
        assert kf_pose is not None
        chosen = self._choose(primary, features, depth, frame, kf_pose, prior)
        if chosen is None:
            return None
        return Step(
            kf_pose @ chosen.T,
            True,
            chosen.T,
            chosen.sigma_m,
            chosen.sigma_deg,
            inliers=chosen.inliers,
            features=features,
            extra=self._skip_edges(features, depth),
            method=chosen.method,
        )

    def keyframe_job(self, frame: Frame, gray: np.ndarray, flowed: Hypothesis, prior: np.ndarray) -> Step | None:
        """A deferred keyframe's step (on another thread): features, then ``keyframe_step`` from their pose, or
        from the flow's when the features fail."""
        depth = frame.depth_m()
        features = self.extractor.extract_gray(gray, depth)
        assert self._kf_features is not None
        try:
            rel = self.estimator.estimate(self._kf_features, features)
            primary = Hypothesis("features", rel.T_a_b, rel.sigma_m, rel.sigma_deg, rel.inliers)
        except Rejected:
            primary = flowed
        return self.keyframe_step(frame, features, depth, primary, prior)

    def accept_keyframe(self, frame: Frame, gray: np.ndarray, step: Step, since: int) -> None:
        """A deferred keyframe becomes the one tracked against; the frames tracked since it stay posed."""
        assert step.features is not None
        last = self._last_pose
        self._new_keyframe(step.pose, step.features, frame.depth_m(), frame, step, gray)
        self._last_pose, self._since = last, since

    def _flow(self, gray: np.ndarray, prior: np.ndarray | None = None) -> Hypothesis | None:
        """``T_kf_frame`` from the keyframe's points followed into ``gray`` (``perception.keyframe_tracker``), or
        None when too few were followed or PnP did not accept them."""
        if not self.tracker.ready and self._kf_gray is not None and self._kf_features is not None:  # restored
            self.tracker.start(self._kf_gray, self._kf_features.pixels, self._kf_features.points)
        if prior is not None and self._kf_pose is not None:  # start the search where the motion prior says
            T_color = self.estimator.E @ prior @ self.estimator.E_inv  # keyframe colour camera -> frame's
            self.tracker.predict(inverse(T_color), self.estimator.K)
        try:
            tracks = self.tracker.track(gray)
        except cv2.error:  # an image of another size than the keyframe's
            return None
        try:
            rel = self.estimator.solve(tracks.points, tracks.pixels)
        except Rejected:
            return None
        return Hypothesis("tracked", rel.T_a_b, rel.sigma_m, rel.sigma_deg, rel.inliers)

    def _keyframe_due(self, h: Hypothesis) -> bool:
        trans, rot = motion_magnitude(h.T)
        p = self.policy
        return (
            trans >= p.translation_m
            or rot >= math.radians(p.rotation_deg)
            or self._since >= p.max_interval
            or h.inliers < p.min_inliers
        )

    def _choose(
        self,
        primary: Hypothesis | None,
        features: Features,
        depth: np.ndarray,
        frame: Frame,
        kf_pose: np.ndarray,
        prior: np.ndarray,
    ) -> Hypothesis | None:
        """The keyframe's pose: the features' PnP (refined by ICP within the correction gate); when the depth does
        not agree with it (``min_agreement``) or the features failed, the fallback chain's candidates compete
        by agreement (against a feature pose, only those far from it). A feature pose that passed its own
        checks is never discarded for lack of agreement."""
        assert self._kf_depth is not None
        cfg, kf_depth = self.config, self._kf_depth
        scored: list[tuple[float, Hypothesis]] = []

        def consider(h: Hypothesis | None) -> None:
            if h is not None:
                scored.append((depth_agreement(depth, kf_depth, self.camera.depth, h.T).fraction, h))

        if primary is not None:
            # an ICP correction within the gate replaces the features' pose; a larger one is not used: PnP and
            # depth ICP disagree by centimetres when colour and depth are misregistered (7-Scenes), and the
            # loop closures are PnP too (letting ICP compete by agreement took 7-Scenes from 4.07 to 5.98 cm)
            consider(replace(primary, T=self._refine(primary.T, depth, kf_depth)))
        best = max(scored, key=lambda x: x[0]) if scored else None
        if best is not None and best[0] >= cfg.min_agreement:
            return best[1]
        if cfg.fallback:
            assert self._kf_features is not None
            kf = (self._kf_features, self._kf_gray, kf_depth)
            for h in self.chain.candidates(kf, features, depth, frame, prior):
                if primary is None or self._far_from(primary, h):
                    consider(h)
            best = max(scored, key=lambda x: x[0]) if scored else None
            if best is not None and best[0] >= cfg.min_agreement:
                return best[1]
        if primary is not None:  # the features' own checks passed: kept (scored first)
            return scored[0][1]
        return None

    def _far_from(self, primary: Hypothesis, h: Hypothesis) -> bool:
        """``h`` differs from the features' pose by more than ``fallback_override_m`` / ``_deg``: only then may
        it replace it. ICP maximises the very agreement it is scored by, so a nearby ICP answer always scores
        a little higher than a sound feature pose; a feature pose tens of centimetres off is another matter."""
        dt, dr = motion_magnitude(relative(primary.T, h.T))
        return dt > self.config.fallback_override_m or math.degrees(dr) > self.config.fallback_override_deg

    def _prediction(self, timestamp: float, kf_pose: np.ndarray) -> np.ndarray:
        """``T_kf_frame`` predicted by constant velocity from the last posed step (the last pose without one)."""
        T_kf_last = inverse(kf_pose) @ self._last_pose
        if self._velocity is None:
            return T_kf_last
        step, dt = self._velocity
        return T_kf_last @ scaled_motion(step, (timestamp - self._last_time) / dt if dt > 0 else 1.0)

    def _skip_edges(self, features: Features, depth: np.ndarray) -> list[tuple[int, np.ndarray, float, float]]:
        """Extra factors to the keyframes before the previous one: (how many back, T_old_new, sigmas)."""
        edges = []
        for back, (old_features, old_depth) in enumerate(reversed(self._history), start=2):
            try:
                rel = self.estimator.estimate(old_features, features)
            except Rejected:
                continue
            edges.append((back, self._refine(rel.T_a_b, depth, old_depth), rel.sigma_m, rel.sigma_deg))
        return edges

    def _refine(self, T_pnp: np.ndarray, depth: np.ndarray, ref_depth: np.ndarray) -> np.ndarray:
        """Depth ICP from the PnP estimate (``_small_correction``)."""
        if not self.config.icp:
            return T_pnp
        result = icp_refine(depth, self._icp_target(ref_depth), self.camera.depth, T_pnp)
        if result is None:
            return T_pnp
        if not self._small_correction(T_pnp, result.T):
            return T_pnp
        self.icp_used += 1
        return result.T

    def _icp_target(self, ref_depth: np.ndarray) -> IcpTarget:
        """``ref_depth`` (a keyframe's) prepared as an ICP target once: every frame refined against it reuses it."""
        held = self._targets.get(id(ref_depth))
        if held is None or held[0] is not ref_depth:
            held = self._targets[id(ref_depth)] = (ref_depth, icp_target(ref_depth, self.camera.depth))
        return held[1]

    def _small_correction(self, T_pnp: np.ndarray, T_icp: np.ndarray) -> bool:
        """ICP moved the features' pose by at most ``icp_max_correction_m`` / ``_deg`` (else it is not used)."""
        dt, dr = motion_magnitude(relative(T_pnp, T_icp))
        return dt <= self.config.icp_max_correction_m and math.degrees(dr) <= self.config.icp_max_correction_deg

    def _posed(self, frame: Frame, step: Step) -> Step:
        """Remember a posed frame for the motion prior."""
        dt = frame.timestamp - self._last_time
        if dt > 0:
            self._velocity = (relative(self._last_pose, step.pose), dt)
        self._last_pose, self._last_time = step.pose, frame.timestamp
        return step

    def _lost(self, frame: Frame, features: Features, depth: np.ndarray, exc: Rejected) -> Step:
        """No pose for this frame. With enough features to track from it becomes a keyframe without an
        odometry factor (tracking re-initialises on it); without (a blank wall) it is left unposed and the
        keyframe stays, so that the next frame with content is tracked against it."""
        self.lost_count += 1
        if int(np.isfinite(features.points[:, 2]).sum()) < self.config.min_matches:
            log.warning("tracking lost at t=%.3f (%s): nothing to track from, frame not posed", frame.timestamp, exc)
            return Step(self._last_pose, False, lost=True, features=features, method="lost", posed=False)
        log.warning("tracking lost at t=%.3f (%s): no odometry factor for this frame", frame.timestamp, exc)
        step = Step(self._last_pose, True, None, lost=True, features=features, method="lost")
        self._velocity = None
        self._last_time = frame.timestamp
        return self._new_keyframe(self._last_pose, features, depth, frame, step)

    @property
    def started(self) -> bool:
        """There is a keyframe to track from."""
        return self._kf_pose is not None

    def follow(self, frame: Frame, pose: np.ndarray, keyframe: bool) -> None:
        """``frame`` was posed at ``pose`` by another source; at a keyframe it becomes this front end's keyframe
        too (its features extracted), so that the next frame can be tracked visually against it."""
        if self.deferral is not None:
            self.deferral.drop()
        self._posed(frame, Step(pose, keyframe))
        if keyframe:
            features = self.extractor.extract(frame)
            self._new_keyframe(pose, features, frame.depth_m(), frame, Step(pose, True, lost=True))

    def restart(self, frame: Frame, pose: np.ndarray) -> Step:
        """Start tracking again at ``frame``, whose pose is only known to be near ``pose`` (the frames in between
        were posed by another source): a lost keyframe, which the core relocalizes or starts a segment with."""
        if self.deferral is not None:
            self.deferral.drop()
        features = self.extractor.extract(frame)
        self._last_pose, self._velocity = pose, None
        return self._lost(frame, features, frame.depth_m(), Rejected("source_switch"))

    def reanchor(self, pose: np.ndarray) -> None:
        """The current keyframe's odometry pose is ``pose`` (after relocalization placed it in the map)."""
        self._kf_pose = self._last_pose = pose

    def _new_keyframe(
        self,
        pose: np.ndarray,
        features: Features,
        depth: np.ndarray,
        frame: Frame,
        step: Step,
        gray: np.ndarray | None = None,
    ) -> Step:
        if step.lost:
            self._history = []
        elif self._kf_features is not None and self._kf_depth is not None:  # not the first keyframe
            self._history = (
                [*self._history, (self._kf_features, self._kf_depth)][-(self.policy.skip_edges - 1) :]
                if self.policy.skip_edges > 1
                else []
            )
        self._kf_pose, self._kf_features, self._kf_depth = pose, features, depth
        kept = {id(depth), *(id(d) for _, d in self._history)}  # ICP targets of keyframes still refined against
        self._targets = {k: v for k, v in self._targets.items() if k in kept}
        flow = self.config.tracker == "flow"
        if gray is None and (flow or self.config.fallback):
            gray = gray_image(frame)
        self._kf_gray = gray if (flow or self.config.fallback) else None
        if flow and gray is not None:
            self.tracker.start(gray, features.pixels, features.points)
        self._since, self._last_pose = 0, pose
        return step
