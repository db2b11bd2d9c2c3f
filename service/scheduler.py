"""The service's scheduler: the SLAM core's keyframe stages on threads beside the tracking.

One mapping thread runs the stages of the ``MAP`` lane in submission order (a keyframe's objects, then its
loop verification). More mapping threads measured worse: they compete with ingest and queries for the GIL
and the two cores (status p99 under overload 125-140 ms with three, 93 ms with one). The detector has a
thread of its own (``DETECT``): onnxruntime releases the GIL, so detecting keyframe k+1 overlaps associating
keyframe k (keyframe mapping on 7-Scenes 12.2 keyframes/s instead of 9.7-10.9, `bench stages`). The core
applies each keyframe's results at a fixed point (``slam.core.MAPPING_LAG``), so the map is bit-identical to
the one ``InlineRunner`` gives.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from slam.runner import Handle, Lane


class ThreadedRunner:
    """Stages on two threads: one per lane."""

    def __init__(self) -> None:
        self._lanes = {
            Lane.MAP: ThreadPoolExecutor(1, thread_name_prefix="objslam-mapping"),
            Lane.DETECT: ThreadPoolExecutor(1, thread_name_prefix="objslam-detector"),
            Lane.KEYFRAME: ThreadPoolExecutor(1, thread_name_prefix="objslam-keyframe"),
        }

    def submit(self, lane: Lane, stage: Callable[..., Any], *args: Any) -> Handle:
        return self._lanes[lane].submit(stage, *args)

    def close(self) -> None:
        """Finish the submitted stages, then stop the threads."""
        for executor in (self._lanes[Lane.KEYFRAME], self._lanes[Lane.DETECT], self._lanes[Lane.MAP]):
            executor.shutdown(wait=True)
