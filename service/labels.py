"""Detection labels from the network, treated as data: a bounded vocabulary and a bounded number per frame.

Labels that robots send become object classes, status keys and counters. Unbounded, 60 frames with 512 fresh
labels each grew the status reply to 1 MB (14,338 classes) and stalled processing. A label is kept when it
is in the vocabulary (``ingest.labels``; default the detector's COCO-80) or among the first
``ingest.extra_labels`` others seen; any later one becomes ``other``. A frame keeps its
``ingest.max_detections`` best-scored detections.
"""

from __future__ import annotations

from dataclasses import replace

from perception.coco import COCO_CLASSES
from perception.frame import Detection, Frame

OTHER = "other"


class LabelVocabulary:
    """Maps a frame's detection labels into a bounded set; counts what it relabelled and dropped."""

    def __init__(self, labels: tuple[str, ...] | None, extra: int, max_detections: int):
        self.known = frozenset(labels if labels is not None else COCO_CLASSES) | {OTHER}
        self.extra, self.max_detections = extra, max_detections
        self.admitted: set[str] = set()
        self.relabelled = self.dropped = 0

    def label(self, label: str) -> str:
        if label in self.known or label in self.admitted:
            return label
        if len(self.admitted) < self.extra:
            self.admitted.add(label)
            return label
        self.relabelled += 1
        return OTHER

    def apply(self, frame: Frame) -> Frame:
        """``frame`` with its detections' labels in the vocabulary and at most ``max_detections`` of them."""
        if not frame.detections:
            return frame
        detections = frame.detections
        if len(detections) > self.max_detections:
            self.dropped += len(detections) - self.max_detections
            detections = sorted(detections, key=lambda d: -d.score)[: self.max_detections]
        kept = [Detection(self.label(d.label), d.score, d.box) for d in detections]
        return replace(frame, detections=kept)

    def counters(self) -> dict[str, int]:
        return {
            "labels_admitted": len(self.admitted),
            "labels_relabelled": self.relabelled,
            "detections_dropped": self.dropped,
        }
