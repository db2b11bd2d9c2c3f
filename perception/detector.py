"""The object detector (SPEC 6.1): an ONNX COCO model run with onnxruntime, decoded into Detections.

Three output layouts are supported, chosen by ``DetectorSettings.kind``: the shipped CenterNet
(default), the shipped NanoDet, and an ultralytics YOLO ONNX export supplied by the user.
See ``docs/detector.md`` and ``models/NOTICE.md``.
"""

from __future__ import annotations

import ast
import logging
import time
from pathlib import Path
from typing import Literal

import numpy as np
import onnxruntime as ort
from pydantic import BaseModel, ConfigDict, Field

from perception.centernet_input import ReshapeError, reshaped_centernet
from perception.coco import COCO_CLASSES
from perception.detector_decoders import (
    NANODET_MEAN_BGR,
    NANODET_STD_BGR,
    InputTransform,
    clip_boxes,
    decode_centernet,
    decode_nanodet,
    decode_yolo,
    fitted_height,
    letterbox,
    select,
    stretch,
)
from perception.frame import Detection

log = logging.getLogger(__name__)

DetectorKind = Literal["centernet", "nanodet", "yolo"]
MODELS_DIR = Path(__file__).resolve().parents[1] / "models"
MODEL_FILES: dict[str, str] = {
    "centernet": "centernet_coco.onnx",
    "nanodet": "nanodet_coco.onnx",
    "yolo": "yolo_coco.onnx",
}
DEFAULT_INPUT_SIZE: dict[str, int] = {"centernet": 512, "nanodet": 416, "yolo": 640}
BUILD_SCRIPT = "scripts/build_detector.sh"

# Tuned on every 10th frame of 7-Scenes redkitchen by inspecting crops sorted by score (docs/detector.md).
# CenterNet's scores are low (heatmap peaks): the floor is 0.3; chairs and the table are found reliably
# from 0.25; magazines and a picture frame score up to 0.43 as "tv", "laptop" or "microwave".
DEFAULT_SCORE_THRESHOLD: dict[str, float] = {"centernet": 0.3, "nanodet": 0.35, "yolo": 0.25}
DEFAULT_CLASS_THRESHOLDS: dict[str, dict[str, float]] = {
    "centernet": {"chair": 0.25, "dining table": 0.25, "book": 0.35, "tv": 0.45, "laptop": 0.45, "microwave": 0.45},
    "nanodet": {
        "chair": 0.3,
        "dining table": 0.3,
        "tv": 0.4,
        "book": 0.4,
        "bottle": 0.45,
        "refrigerator": 0.45,
        "sink": 0.45,
        "oven": 0.45,
        "bed": 0.45,
        "cell phone": 0.45,
    },
    "yolo": {},
}


class DetectorSettings(BaseModel):
    """The ONNX object detector (SPEC 6.1), used on keyframes whose frames carry no detections: what model to
    run and how to filter its output."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    enabled: bool = Field(default=True, description="run on keyframes whose frames carry no detections")
    kind: DetectorKind = Field(
        default="centernet",
        description='output layout: "centernet" and "nanodet" (shipped, COCO-80) or "yolo" (ultralytics)',
    )
    model: Path | None = Field(default=None, description="ONNX file; empty = the shipped model of `kind` in models/")
    threads: int = Field(default=2, ge=1, description="onnxruntime intra-op threads")
    score_threshold: float | None = Field(
        default=None,
        ge=0,
        le=1,
        description="minimum score of classes without a per-class one; empty = tuned default of `kind`",
    )
    class_thresholds: dict[str, float] | None = Field(
        default=None,
        description="per-class minimum scores by label, replacing the defaults; empty = tuned defaults of `kind`",
    )
    nms_iou: float = Field(
        default=0.5,
        gt=0,
        le=1,
        description="class-aware NMS: a box is dropped when its IoU with a better one exceeds this",
    )
    max_detections: int = Field(default=50, ge=1, description="at most this many detections per image, best first")
    classes: tuple[str, ...] | None = Field(default=None, description="allow-list of labels to report; empty = all")
    input_size: int | None = Field(
        default=None, ge=32, description="square network input side; empty = the model's (512 / 416 / 640 when dynamic)"
    )
    fit_aspect: bool = Field(
        default=False,
        description="centernet: a 512-wide input as high as the image's aspect needs "
        "(512 x 384 for 4:3) instead of the letterboxed 512 x 512: faster, fewer detections",
    )
    """CenterNet: letterbox into an input ``input_size`` wide and as high as the image's aspect needs (a
    multiple of 32: 512 x 384 for 4:3), running the network reshaped for it (``centernet_input``), instead
    of into the square. A quarter less computation for 4:3 cameras, but fewer detections (on 7-Scenes 9 %
    fewer, objects touching the image border score lower): off by default (`objslam bench detector`)."""
    class_names: tuple[str, ...] | None = Field(
        default=None, description="labels by class index; empty = the model's `names` metadata (ultralytics) or COCO-80"
    )

    def thresholds(self) -> tuple[float, dict[str, float]]:
        """The score floor and the per-class thresholds in effect (defaults for ``kind`` filled in)."""
        floor = self.score_threshold if self.score_threshold is not None else DEFAULT_SCORE_THRESHOLD[self.kind]
        per_class = self.class_thresholds if self.class_thresholds is not None else DEFAULT_CLASS_THRESHOLDS[self.kind]
        return floor, dict(per_class)


def default_model_path(kind: str) -> Path:
    """The shipped model for ``kind`` in the repository's ``models/`` directory."""
    if kind not in MODEL_FILES:
        raise ValueError(f"unknown detector kind {kind!r}; expected one of {sorted(MODEL_FILES)}")
    path = MODELS_DIR / MODEL_FILES[kind]
    if not path.is_file():
        hint = (
            f"rebuild it with {BUILD_SCRIPT}"
            if kind != "yolo"
            else "export one with ultralytics (`yolo export model=yolov8n.pt format=onnx`) and put it "
            "there or set the detector model path"
        )
        raise FileNotFoundError(f"detector model not found: {path}; {hint}")
    return path


def _metadata_names(session: ort.InferenceSession) -> tuple[str, ...] | None:
    """Class names from an ultralytics export's ``names`` metadata ("{0: 'person', ...}"), if any."""
    raw = session.get_modelmeta().custom_metadata_map.get("names")
    if not raw:
        return None
    try:
        names = ast.literal_eval(raw)
        return tuple(str(names[i]) for i in sorted(names))
    except (ValueError, SyntaxError, TypeError, KeyError):
        log.warning("ignoring unreadable 'names' metadata in the detector model")
        return None


class Detector:
    """Runs one ONNX detector on RGB images; ``last_ms`` is the time of the latest ``detect`` call."""

    def __init__(self, config: DetectorSettings | None = None) -> None:
        self.config = config if config is not None else DetectorSettings()
        if self.config.kind not in DEFAULT_INPUT_SIZE:
            raise ValueError(
                f"unknown detector kind {self.config.kind!r}; expected one of {sorted(DEFAULT_INPUT_SIZE)}"
            )
        path = Path(self.config.model) if self.config.model else default_model_path(self.config.kind)
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = self.config.threads
        opts.inter_op_num_threads = 1
        # The detector shares the cores with ingest and the graph: idle workers sleep instead of spinning
        # (on the loaded 2-core machine this halved CPU per frame with 2 threads).
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        self._path, self._options = path, opts
        self.session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        self._input = self.session.get_inputs()[0]
        outputs = [o.name for o in self.session.get_outputs()]
        # CenterNet: only its decoded detections are needed (not the heatmap and size maps).
        self._outputs = ["tower_0/detections"] if "tower_0/detections" in outputs else None
        self.input_size = self._input_size()
        self._sessions = {self.input_size: self.session}  # CenterNet by input height
        self.class_names = self._class_names()
        self._thresholds = self._threshold_vector()
        self.last_ms = 0.0
        log.info(
            "detector %s (%s) input %d, %d classes, %d threads",
            path.name,
            self.config.kind,
            self.input_size,
            len(self.class_names),
            self.config.threads,
        )

    def _input_size(self) -> int:
        if self.config.input_size:
            return self.config.input_size
        shape = self._input.shape
        side = shape[1] if self.config.kind == "centernet" else shape[2]  # NHWC vs NCHW
        return side if isinstance(side, int) else DEFAULT_INPUT_SIZE[self.config.kind]

    def _class_names(self) -> tuple[str, ...]:
        if self.config.class_names:
            return tuple(self.config.class_names)
        if self.config.kind == "yolo":
            return _metadata_names(self.session) or COCO_CLASSES
        return COCO_CLASSES

    def _threshold_vector(self) -> np.ndarray:
        """Per-class-index minimum score; inf for classes outside the allow-list."""
        floor, per_class = self.config.thresholds()
        unknown = (set(per_class) | set(self.config.classes or ())) - set(self.class_names)
        if unknown:
            log.warning("detector config names labels the model does not have: %s", sorted(unknown))
        thr = np.array([per_class.get(n, floor) for n in self.class_names], np.float32)
        if self.config.classes is not None:
            thr[[n not in self.config.classes for n in self.class_names]] = np.inf
        return thr

    def preprocess(self, rgb: np.ndarray) -> tuple[np.ndarray, InputTransform]:
        """The network input tensor for ``rgb`` and the image -> input mapping."""
        size, kind = self.input_size, self.config.kind
        if kind == "centernet":  # NHWC RGB 0..255, letterbox with zeros
            img, tf = letterbox(rgb, size, 0, self._centernet_height(rgb.shape[1], rgb.shape[0]))
            return img[None].astype(np.float32), tf
        if kind == "nanodet":  # NCHW BGR, stretched, mean/std normalised
            img, tf = stretch(rgb[..., ::-1], size)
            img = (img.astype(np.float32) - NANODET_MEAN_BGR) / NANODET_STD_BGR
            return img.transpose(2, 0, 1)[None].copy(), tf
        img, tf = letterbox(rgb, size, 114)  # yolo: NCHW RGB 0..1, letterbox with grey 114
        return (img.astype(np.float32) / 255.0).transpose(2, 0, 1)[None].copy(), tf

    def _centernet_height(self, width: int, height: int) -> int:
        """The input height for an image (``fit_aspect``), with its reshaped session made on first use."""
        fitted = fitted_height(width, height, self.input_size) if self.config.fit_aspect else self.input_size
        if fitted not in self._sessions:
            try:
                model = reshaped_centernet(self._path, fitted)
                self._sessions[fitted] = ort.InferenceSession(model, self._options, providers=["CPUExecutionProvider"])
                log.info("detector: CenterNet input %d x %d for %d x %d images", self.input_size, fitted, width, height)
            except (ReshapeError, OSError, RuntimeError) as exc:  # a user's CenterNet of another layout
                log.warning(
                    "detector: cannot run %s at %d x %d (%s); using the square input",
                    self._path.name,
                    self.input_size,
                    fitted,
                    exc,
                )
                self._sessions[fitted] = self.session
        session = self._sessions[fitted]
        return fitted if session is not self.session else self.input_size

    def _decode(self, outputs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self.config.kind == "centernet":
            return decode_centernet(next(o for o in outputs if o.shape[-1] == 6))
        if self.config.kind == "nanodet":
            return decode_nanodet(outputs, self.input_size)
        return decode_yolo(outputs[0], len(self.class_names))

    def infer(self, rgb: np.ndarray) -> tuple[list[np.ndarray], InputTransform]:
        """Raw network outputs for an RGB image, and the image -> network-input mapping."""
        tensor, transform = self.preprocess(np.ascontiguousarray(rgb))
        session = self._sessions.get(tensor.shape[1], self.session) if self.config.kind == "centernet" else self.session
        return session.run(self._outputs, {self._input.name: tensor}), transform

    def detect(self, rgb: np.ndarray) -> list[Detection]:
        """Objects in an HxWx3 uint8 RGB image, best first, boxes in its pixels."""
        if rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"expected an HxWx3 RGB image, got shape {rgb.shape}")
        start = time.perf_counter()
        # 1. Resize / normalise into the network's input layout and run the network.
        outputs, transform = self.infer(rgb)
        # 2. Decode to boxes in input pixels, map back to the image and clip.
        boxes, scores, classes = self._decode(outputs)
        boxes = clip_boxes(transform.to_image(boxes), rgb.shape[1], rgb.shape[0])
        # 3. Per-class thresholds, allow-list, class-aware NMS, at most max_detections.
        keep = select(boxes, scores, classes, self._thresholds, self.config.nms_iou, self.config.max_detections)
        dets = [
            Detection(
                self.class_names[int(classes[i])],
                float(scores[i]),
                (float(boxes[i, 0]), float(boxes[i, 1]), float(boxes[i, 2]), float(boxes[i, 3])),
            )
            for i in keep
        ]
        self.last_ms = (time.perf_counter() - start) * 1000.0
        return dets
