"""A keyframe's mapping as stages: detection, objects, loop verification (Sec. 2.4, 3.8; SPEC 6.1-6.9).

Each stage reads only what it is given and mutates only the component it owns (the detector, the object
map, the loop index), never the graph: so they can run beside the tracking, and their results are applied
to the graph by the core at a fixed point.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from loops.closer import LoopCloser
from loops.records import Candidate, KeyframeEntry
from perception.frame import Detection, Frame
from perception.object_map import ObjectMapper
from perception.odometry import FeatureExtractor
from perception.registration import depth_in_color
from slam.records import KeyframeLoops, KeyframeObjects
from slam.runner import Handle

if TYPE_CHECKING:  # the detector module imports onnxruntime: only where a detector is built
    from perception.detector import Detector


def detect(detector: Detector, rgb: np.ndarray) -> tuple[list[Detection], dict[str, float]]:
    """The detector's objects in a keyframe's colour image, and its time."""
    t0 = time.perf_counter()
    detections = detector.detect(rgb)
    return detections, {"detector": time.perf_counter() - t0}


def map_objects(
    mapper: ObjectMapper | None,
    kf: int,
    frame: Frame,
    detections: Handle,
    body: np.ndarray,
    color_from_body: np.ndarray,
    reposed: np.ndarray | None,
) -> KeyframeObjects:
    """Associate the keyframe's detections, extend tracks and re-cluster objects (Sec. 2.4, SPEC 6.2-6.7).

    ``detections`` is the detection stage's handle (or the frame's own). ``reposed``: new poses of the
    earlier keyframes to recompute the feature vectors from first (Sec. 2.4.7). Boxes are colour pixels, so
    depth is registered to colour and the colour camera's pose is used.
    """
    found, timings = detections.result()
    looked = found is not None  # None: the detector skipped this keyframe (mapping was behind)
    found = found or []
    result = KeyframeObjects(kf, found, timings=dict(timings))
    if mapper is None:
        return result
    if reposed is not None:
        t0 = time.perf_counter()
        mapper.repose(reposed @ color_from_body)
        result.reposed = True
        result.timings["repose"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    camera = frame.camera
    depth = depth_in_color(frame.depth_m(), camera, scale=2)
    result.reclustered = mapper.add_keyframe(kf, found, depth, camera.color, body @ color_from_body, looked)
    to_body = np.linalg.inv(color_from_body)
    result.observations = [
        (t, to_body[:3, :3] @ p + to_body[:3, 3], extent) for t, p, extent in mapper.last_observations
    ]
    result.objects = list(mapper.objects)  # the mapper may be on a later keyframe when this is applied
    result.retired = tuple(mapper.take_retired())
    result.unconfirmed = len(mapper.clusterer.unkept)
    result.timings["objects"] = time.perf_counter() - t0
    return result


def verify_loops(
    closer: LoopCloser,
    extractor: FeatureExtractor,
    entry: KeyframeEntry,
    frame: Frame,
    proposed: list[Candidate],
    poses: np.ndarray | None,
) -> KeyframeLoops:
    """Loop-closure candidates of a keyframe, verified geometrically (no graph: ``poses`` are given)."""
    t0 = time.perf_counter()
    if entry.features is None:
        entry = replace(entry, features=extractor.extract(frame))
    verified = closer.verify(entry, frame.rgb, proposed, poses)
    return KeyframeLoops(verified, {"loop_closure": time.perf_counter() - t0})
