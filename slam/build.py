"""The SLAM core's components built from the configuration (the one place that knows every section)."""

from __future__ import annotations

from pathlib import Path

from graph.object_landmarks import ObjectLandmarks
from graph.window import WindowedGraph
from loops.closer import LoopCloser
from perception.frame import CameraModel
from perception.frontend import VisualOdometry
from perception.object_map import ObjectMapper
from perception.odometry import FeatureExtractor, RelativePoseEstimator
from perception.odometry_choice import PerFrameOdometry
from rl.proposer import PolicyProposer
from slam.core import SlamCore, Tracking, TrackingFactory
from slam.runner import Runner
from slam.settings import SlamConfig


def load_proposer(path: Path | None, radius: int, candidates: int) -> PolicyProposer:
    """The RL loop-closure proposer for a policy file (``loops.policy``)."""
    from rl.policy import OnnxPolicy  # onnxruntime session only when a policy is configured

    if path is None:
        raise ValueError("loops.source policy/both needs loops.policy (a FILE.onnx from train-lc --from-map)")
    return PolicyProposer(OnnxPolicy(path), radius=radius, max_candidates=candidates)


def tracking_factory(settings: SlamConfig, graph: WindowedGraph) -> TrackingFactory:
    """Builds the front end (each frame's own odometry, else visual odometry) and loop closure for the first
    frame's camera."""
    policy, odometry = settings.keyframes, settings.odometry

    def build(camera: CameraModel, external: bool) -> Tracking:
        def visual() -> VisualOdometry:
            return VisualOdometry(camera, policy, odometry)

        frontend = PerFrameOdometry(policy, visual if odometry.visual else None)
        if odometry.visual:  # built now: it follows the odometry frames, ready to take over when it drops out
            frontend.visual = visual()
        if settings.loops.source == "off":
            return Tracking(camera, frontend)
        loops = LoopCloser(graph, RelativePoseEstimator(camera, odometry), settings.loops)
        return Tracking(camera, frontend, loops, FeatureExtractor(camera, odometry))

    return build


def new_graph(settings: SlamConfig) -> WindowedGraph:
    """An empty bounded pose graph."""
    return WindowedGraph(settings.graph)


def build_core(settings: SlamConfig, runner: Runner | None = None, graph: WindowedGraph | None = None) -> SlamCore:
    """A SLAM core for ``settings``, its stages run by ``runner`` (default: at once), on ``graph`` (default:
    a new one)."""
    graph = graph if graph is not None else new_graph(settings)
    objects_on = settings.objects.enabled
    loops = settings.loops
    proposer = load_proposer(loops.policy, loops.policy_radius, loops.policy_candidates) if loops.uses_policy else None

    detector_settings = settings.detector

    def detector():  # built at the first keyframe that needs it (onnxruntime session)
        from perception.detector import Detector

        return Detector(detector_settings)

    return SlamCore(
        settings,
        graph,
        tracking_factory(settings, graph),
        objects=ObjectMapper() if objects_on else None,
        landmarks=ObjectLandmarks(graph, settings.objects) if objects_on and settings.objects.landmarks else None,
        proposer=proposer,
        detector=detector,
        runner=runner,
    )
