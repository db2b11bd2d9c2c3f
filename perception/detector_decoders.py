"""Pure pre- and post-processing for ONNX detectors: resizing, output decoding, thresholds and NMS.

Every function takes and returns numpy arrays, so each step can be tested on constructed tensors.
Boxes are ``(N, 4)`` float arrays ``x1, y1, x2, y2``; decoders return them in network-input pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

NANODET_MEAN_BGR = np.array([103.53, 116.28, 123.675], dtype=np.float32)
NANODET_STD_BGR = np.array([57.375, 57.12, 58.395], dtype=np.float32)


@dataclass(frozen=True)
class InputTransform:
    """Image -> network input mapping: ``x_in = x_img * sx + pad_x`` (and likewise for y)."""

    sx: float
    sy: float
    pad_x: float = 0.0
    pad_y: float = 0.0

    def to_image(self, boxes: np.ndarray) -> np.ndarray:
        """Boxes in network-input pixels -> boxes in image pixels (the inverse mapping)."""
        out = np.asarray(boxes, dtype=np.float32).copy()
        out[:, [0, 2]] = (out[:, [0, 2]] - self.pad_x) / self.sx
        out[:, [1, 3]] = (out[:, [1, 3]] - self.pad_y) / self.sy
        return out


def letterbox(
    image: np.ndarray, size: int, pad_value: int = 0, height: int | None = None
) -> tuple[np.ndarray, InputTransform]:
    """Aspect-preserving resize into a ``size`` wide, ``height`` (default ``size``) high canvas, centred, padded
    with ``pad_value``."""
    h, w = image.shape[:2]
    out_h = size if height is None else height
    scale = min(out_h / h, size / w)
    new_w, new_h = min(size, round(w * scale)), min(out_h, round(h * scale))
    resized = cv2.resize(image, (new_w, new_h), interpolation=cv2.INTER_LINEAR)
    pad_x, pad_y = (size - new_w) // 2, (out_h - new_h) // 2
    canvas = np.full((out_h, size, image.shape[2]), pad_value, dtype=image.dtype)
    canvas[pad_y : pad_y + new_h, pad_x : pad_x + new_w] = resized
    return canvas, InputTransform(scale, scale, float(pad_x), float(pad_y))


def fitted_height(width: int, height: int, size: int, multiple: int = 32) -> int:
    """Input height for a ``size``-wide network input that follows a ``width`` x ``height`` image's aspect:
    the next multiple of ``multiple``, at most ``size`` (384 for 4:3 at 512, 512 for square or portrait)."""
    return min(size, -(-round(size * height / width) // multiple) * multiple)


def stretch(image: np.ndarray, size: int) -> tuple[np.ndarray, InputTransform]:
    """Resize to ``size`` x ``size`` ignoring the aspect ratio."""
    h, w = image.shape[:2]
    resized = cv2.resize(image, (size, size), interpolation=cv2.INTER_LINEAR)
    return resized, InputTransform(size / w, size / h)


def clip_boxes(boxes: np.ndarray, width: int, height: int) -> np.ndarray:
    """Clip boxes to the image ``[0, width] x [0, height]``."""
    out = boxes.copy()
    out[:, [0, 2]] = np.clip(out[:, [0, 2]], 0.0, float(width))
    out[:, [1, 3]] = np.clip(out[:, [1, 3]], 0.0, float(height))
    return out


def decode_centernet(detections: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CenterNet rows ``x1, y1, x2, y2, score, class`` ([1, K, 6] or [K, 6]) -> boxes, scores, classes."""
    rows = np.asarray(detections, dtype=np.float32).reshape(-1, 6)
    return rows[:, :4], rows[:, 4], rows[:, 5].astype(np.int64)


def _softmax(x: np.ndarray, axis: int) -> np.ndarray:
    e = np.exp(x - x.max(axis=axis, keepdims=True))
    return e / e.sum(axis=axis, keepdims=True)


def decode_nanodet(
    outputs: list[np.ndarray], input_size: int, strides: tuple[int, ...] = (8, 16, 32), bins: int = 11
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """NanoDet GFL heads -> boxes, best-class scores, classes.

    ``outputs`` holds, in any order, per stride one ``cls`` tensor [1, N, C] (already sigmoid) and one
    ``reg`` tensor [1, N, 4 * bins] (left, top, right, bottom distances as distributions over ``bins`` bins), with
    ``N = (input_size / stride) ** 2`` cells in row-major order. Distance = softmax expectation x stride,
    measured from the cell centre ``((col + 0.5) * stride, (row + 0.5) * stride)``.
    """
    by_cells: dict[int, list[np.ndarray]] = {}
    for out in outputs:
        arr = np.asarray(out, dtype=np.float32)
        by_cells.setdefault(arr.shape[-2], []).append(arr.reshape(arr.shape[-2], arr.shape[-1]))
    boxes, scores, classes = [], [], []
    for stride in strides:
        grid = input_size // stride
        pair = by_cells.get(grid * grid)
        if pair is None or len(pair) != 2:
            raise ValueError(f"NanoDet: expected a cls and a reg output with {grid * grid} cells for stride {stride}")
        reg, cls = pair if pair[0].shape[1] == 4 * bins else pair[::-1]
        dist = _softmax(reg.reshape(-1, 4, bins), axis=2) @ np.arange(bins, dtype=np.float32) * stride
        idx = np.arange(grid * grid)
        cx, cy = (idx % grid + 0.5) * stride, (idx // grid + 0.5) * stride
        boxes.append(np.stack([cx - dist[:, 0], cy - dist[:, 1], cx + dist[:, 2], cy + dist[:, 3]], axis=1))
        classes.append(cls.argmax(axis=1))
        scores.append(cls.max(axis=1))
    return np.concatenate(boxes).astype(np.float32), np.concatenate(scores), np.concatenate(classes)


def decode_yolo(output: np.ndarray, num_classes: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ultralytics YOLO (v8/v11) output [1, 4 + C, N] (or [1, N, 4 + C]): ``cx, cy, w, h`` + class scores.

    There is no objectness: the score is the best class score. The channel axis is the one of size
    ``4 + num_classes``; when that is unknown or ambiguous, the shorter axis (anchors outnumber channels).
    """
    arr = np.asarray(output, dtype=np.float32)
    arr = arr.reshape(arr.shape[-2], arr.shape[-1])
    channels_first = arr.shape[0] < arr.shape[1]
    if num_classes is not None and (arr.shape[0] == 4 + num_classes) != (arr.shape[1] == 4 + num_classes):
        channels_first = arr.shape[0] == 4 + num_classes
    if channels_first:
        arr = arr.T
    cxcywh, cls = arr[:, :4], arr[:, 4:]
    half = cxcywh[:, 2:4] / 2
    boxes = np.concatenate([cxcywh[:, :2] - half, cxcywh[:, :2] + half], axis=1)
    return boxes, cls.max(axis=1), cls.argmax(axis=1)


def iou_one_to_many(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Intersection over union of one box with each of ``boxes``."""
    iw = np.clip(np.minimum(box[2], boxes[:, 2]) - np.maximum(box[0], boxes[:, 0]), 0.0, None)
    ih = np.clip(np.minimum(box[3], boxes[:, 3]) - np.maximum(box[1], boxes[:, 1]), 0.0, None)
    inter = iw * ih
    area = (box[2] - box[0]) * (box[3] - box[1])
    areas = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    return inter / np.maximum(area + areas - inter, 1e-9)


def nms(boxes: np.ndarray, scores: np.ndarray, classes: np.ndarray, iou: float, max_det: int) -> np.ndarray:
    """Class-aware greedy NMS: indices of kept boxes, best score first, at most ``max_det``."""
    order = np.argsort(-scores, kind="stable")
    # Shift each class to its own region of the plane so boxes of different classes never overlap.
    span = float(np.abs(boxes).max()) + 1.0 if len(boxes) else 0.0
    shifted = boxes.astype(np.float64) + (classes.astype(np.float64) * 2.0 * span)[:, None]
    keep: list[int] = []
    while order.size and len(keep) < max_det:
        i = order[0]
        keep.append(int(i))
        rest = order[1:]
        order = rest[iou_one_to_many(shifted[i], shifted[rest]) <= iou]
    return np.array(keep, dtype=np.int64)


def select(
    boxes: np.ndarray, scores: np.ndarray, classes: np.ndarray, thresholds: np.ndarray, iou: float, max_det: int
) -> np.ndarray:
    """Indices that pass the per-class score ``thresholds`` (indexed by class; inf = excluded), then NMS."""
    valid = (classes >= 0) & (classes < len(thresholds))
    passed = np.flatnonzero(valid)
    passed = passed[scores[passed] >= thresholds[classes[passed]]]
    passed = passed[(boxes[passed, 2] > boxes[passed, 0]) & (boxes[passed, 3] > boxes[passed, 1])]
    return passed[nms(boxes[passed], scores[passed], classes[passed], iou, max_det)]
