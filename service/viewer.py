"""The map as a Rerun scene: camera, trajectories, objects, loop closures, map points (``ViewerSink``).

Entities (world frame = the first camera's, x right, y down, z forward)::

    world/camera              pose (Transform3D) and pinhole; rgb, depth, detections at keyframes
    world/trajectory          optimised poses, re-logged when the graph moved
    world/odometry            the front end's poses
    world/ground_truth        aligned ground truth (``run`` on a dataset with it)
    world/objects             ellipsoids (the objects' axes) coloured by class, "label #id (n obs)"
    world/landmarks           the objects' iSAM2 landmarks
    world/loops/accepted      loop closures as segments between keyframes, labelled by source
    world/loops/rejected      the refused candidates, labelled by reason
    world/map_points          sparse map points

Timelines: ``frame`` (frames processed) and ``sensor_time`` (the newest pose's timestamp).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from scipy.spatial.transform import Rotation

from graph.trajectory import Trajectory
from perception.clustering import ClusterConfig
from perception.frame import CameraModel, Detection
from service.map_summary import MapSummary
from service.protocol import Inspected

SIGMAS = ClusterConfig().axis_scale  # ellipsoid half-axes in standard deviations, as objects.json's axes
MAX_STRIP_POINTS = 2000  # a trajectory is decimated to this many poses when logged
MAX_MAP_POINTS = 50_000
EPOCH_S = 1e8  # timestamps above this are Unix times (TUM), below seconds from the start (synthetic)
PALETTE = np.array(  # tab10
    [
        [31, 119, 180],
        [255, 127, 14],
        [44, 160, 44],
        [214, 39, 40],
        [148, 103, 189],
        [140, 86, 75],
        [227, 119, 194],
        [127, 127, 127],
        [188, 189, 34],
        [23, 190, 207],
    ],
    np.uint8,
)
OPTIMISED, ODOMETRY, TRUTH = (31, 119, 180), (255, 127, 14), (160, 160, 160)
ACCEPTED, REJECTED = (44, 160, 44), (214, 39, 40)
IMAGE_MEDIA = {"jpeg": "image/jpeg", "png": "image/png"}


@dataclass(frozen=True)
class ViewerUpdate:
    """What one update shows: the map as of ``frame`` frames processed; None fields are unchanged."""

    frame: int
    time: float
    summary: MapSummary
    pose: np.ndarray | None = None  # the newest camera-to-world pose
    trajectory: Trajectory | None = None  # given when the graph moved
    odometry: Trajectory | None = None
    message: Inspected | None = None  # a keyframe's frame, its images still encoded
    detections: list[Detection] | None = None  # that keyframe's boxes (None: the ones its message carries)
    late_boxes: tuple[int, float, list[Detection]] | None = None  # (frame, time, boxes) of an earlier keyframe
    points: np.ndarray | None = None
    ground_truth: np.ndarray | None = None  # (N, 3) positions aligned to the trajectory


def blueprint() -> rrb.Blueprint:
    """The layout: the 3D map (without the depth cloud) beside the camera's image and its depth."""
    camera_2d = ["world/camera/rgb", "world/camera/detections"]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="map", origin="world", contents=["+ world/**", "- world/camera/depth"]),
            rrb.Vertical(
                rrb.Spatial2DView(name="camera", origin="world/camera", contents=camera_2d),
                rrb.Spatial2DView(name="depth", origin="world/camera", contents=["world/camera/depth"]),
            ),
            column_shares=[3, 1],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed"),
    )


def class_colour(label: str) -> tuple[int, int, int]:
    """A fixed colour per class name (the same in every run)."""
    r, g, b = PALETTE[zlib.crc32(label.encode()) % len(PALETTE)]
    return int(r), int(g), int(b)


def ellipsoid(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Half-axes (``SIGMAS`` standard deviations) and rotation quaternion (x, y, z, w) of a 3x3 covariance."""
    half, quats = ellipsoids(np.asarray(cov, float)[None])
    return half[0], quats[0]


def ellipsoids(covs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``ellipsoid`` of each of N 3x3 covariances at once: half-axes (N, 3) and quaternions (N, 4)."""
    covs = np.asarray(covs, float).reshape(-1, 3, 3)
    if not len(covs):
        return np.zeros((0, 3)), np.zeros((0, 4))
    values, vectors = np.linalg.eigh(covs)
    vectors[np.linalg.det(vectors) < 0, :, -1] *= -1  # rotations, not reflections
    half = SIGMAS * np.sqrt(np.clip(values, 1e-8, None))
    return half, Rotation.from_matrix(vectors).as_quat()


def decimate(points: np.ndarray, limit: int) -> np.ndarray:
    """At most ``limit`` of ``points``, evenly strided, the last one kept."""
    if len(points) <= limit:
        return points
    idx = np.linspace(0, len(points) - 1, limit).round().astype(int)
    return points[idx]


class ViewerSink:
    """Logs ``ViewerUpdate``s to a Rerun recording stream. Not thread-safe: one thread (the feed's) calls it."""

    def __init__(self, recording: rr.RecordingStream, camera: CameraModel | None = None):
        self.rec = recording
        self.camera: CameraModel | None = None
        self._epoch: bool | None = None
        self._objects_key: object = None
        self._loops_key: object = None
        self._stamps, self._positions = np.zeros(0), np.zeros((0, 3))  # the trajectory's, by time
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)
        if camera is not None:
            self._log_pinhole(camera)

    def log(self, update: ViewerUpdate) -> None:
        """Everything in ``update`` that changed since the last one."""
        if update.late_boxes is not None:  # at the time its keyframe's image was logged
            self._set_time(*update.late_boxes[:2])
            self._log_boxes(update.late_boxes[2])
        self._set_time(update.frame, update.time)
        if update.pose is not None:
            self.rec.log("world/camera", rr.Transform3D(translation=update.pose[:3, 3], mat3x3=update.pose[:3, :3]))
        if update.message is not None:
            self._log_images(update.message)
            dets = update.detections if update.detections is not None else update.message.detections
            self._log_boxes(dets or [])
        if update.trajectory is not None:
            self._log_trajectory("world/trajectory", update.trajectory, OPTIMISED)
            order = np.argsort(update.trajectory.timestamps, kind="stable")
            self._stamps = np.asarray(update.trajectory.timestamps, float)[order]
            self._positions = update.trajectory.poses[order, :3, 3]
        if update.odometry is not None:
            self._log_trajectory("world/odometry", update.odometry, ODOMETRY)
        summary = update.summary
        if summary.objects_key != self._objects_key:
            self._log_objects(summary.objects)
            self._objects_key = summary.objects_key
        if summary.loops_key != self._loops_key or (update.trajectory is not None and summary.loops):
            self._log_loops(summary.loops)
            self._loops_key = summary.loops_key
        if update.points is not None:
            pts = decimate(np.asarray(update.points, np.float32), MAX_MAP_POINTS)
            self.rec.log("world/map_points", rr.Points3D(pts, radii=0.005, colors=(120, 120, 120)))
        if update.ground_truth is not None:
            self._log_strip("world/ground_truth", update.ground_truth, TRUTH, "ground truth (aligned)")

    def _set_time(self, frame: int, when: float) -> None:
        self.rec.set_time("frame", sequence=frame)
        if self._epoch is None:
            self._epoch = when > EPOCH_S
        if self._epoch:
            self.rec.set_time("sensor_time", timestamp=when)
        else:
            self.rec.set_time("sensor_time", duration=when)

    def _log_pinhole(self, camera: CameraModel) -> None:
        self.camera = camera
        self.rec.log(
            "world/camera",
            rr.Pinhole(
                image_from_camera=camera.color.matrix(),
                resolution=[camera.width, camera.height],
                image_plane_distance=0.3,
            ),
            static=True,
        )

    def _log_images(self, message: Inspected) -> None:
        """Colour and depth (when registered to colour) of a keyframe, its images as they came."""
        if self.camera is None or self.camera != message.camera:
            self._log_pinhole(message.camera)
        camera, meta = message.camera, message.color_meta
        if meta["encoding"] in IMAGE_MEDIA:
            image = rr.EncodedImage(contents=bytes(message.color), media_type=IMAGE_MEDIA[meta["encoding"]])
            self.rec.log("world/camera/rgb", image)
        else:  # rgb8
            pixels = np.frombuffer(message.color, np.uint8).reshape(meta["height"], meta["width"], 3)
            self.rec.log("world/camera/rgb", rr.Image(pixels))
        if camera.registered:
            if message.depth_meta["encoding"] == "png16":
                depth = rr.EncodedDepthImage(bytes(message.depth), media_type="image/png", meter=camera.depth_scale)
                self.rec.log("world/camera/depth", depth)
            else:  # u16le
                d = np.frombuffer(message.depth, "<u2").reshape(message.depth_meta["height"], -1)
                self.rec.log("world/camera/depth", rr.DepthImage(d, meter=camera.depth_scale))

    def _log_boxes(self, dets: list[Detection]) -> None:
        self.rec.log(
            "world/camera/detections",
            rr.Boxes2D(
                array=np.array([d.box for d in dets], float).reshape(-1, 4),
                array_format=rr.Box2DFormat.XYXY,
                labels=[f"{d.label} {d.score:.2f}" for d in dets],
                colors=[class_colour(d.label) for d in dets],
            ),
        )

    def _log_trajectory(self, entity: str, trajectory: Trajectory, colour: tuple[int, int, int]) -> None:
        self._log_strip(entity, trajectory.poses[:, :3, 3], colour, None)

    def _log_strip(self, entity: str, points: np.ndarray, colour: tuple[int, int, int], label: str | None) -> None:
        strip = decimate(np.asarray(points, np.float32), MAX_STRIP_POINTS)
        self.rec.log(entity, rr.LineStrips3D([strip], colors=[colour], radii=0.01, labels=label))

    def _log_objects(self, objects: list[dict]) -> None:
        half, quats = ellipsoids(np.array([o["cov"] for o in objects], float))
        self.rec.log(
            "world/objects",
            rr.Ellipsoids3D(
                centers=np.array([o["mean"] for o in objects], float).reshape(-1, 3),
                half_sizes=half,
                quaternions=quats,
                colors=[class_colour(o["label"]) for o in objects],
                labels=[f"{o['label']} #{o['id']} ({o['n_observations']} obs)" for o in objects],
                show_labels=True,
            ),
        )
        marks = [o for o in objects if o.get("landmark") is not None]
        self.rec.log(
            "world/landmarks",
            rr.Points3D(
                np.array([o["landmark"] for o in marks], float).reshape(-1, 3),
                radii=0.03,
                colors=[class_colour(o["label"]) for o in marks],
            ),
        )

    def _log_loops(self, loops: list[dict]) -> None:
        for accepted, entity, colour in ((True, "accepted", ACCEPTED), (False, "rejected", REJECTED)):
            segments, labels = [], []
            for r in loops:
                a, b = self._position(float(r["match_t"])), self._position(float(r["query_t"]))
                if bool(r["accepted"]) == accepted and a is not None and b is not None:
                    segments.append(np.stack([a, b]))
                    labels.append(r["source"] if accepted else str(r.get("reason")))
            self.rec.log(
                f"world/loops/{entity}",
                rr.LineStrips3D(segments, colors=[colour] * len(segments), radii=0.008, labels=labels),
            )

    def _position(self, timestamp: float) -> np.ndarray | None:
        """The optimised position of the frame at ``timestamp``, None when it is not in the trajectory."""
        i = int(np.searchsorted(self._stamps, timestamp))
        return self._positions[i] if i < len(self._stamps) and self._stamps[i] == timestamp else None
