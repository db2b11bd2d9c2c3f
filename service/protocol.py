"""Protocol v1 of ``<prefix>/<robot>/rgbd``: encoding and validating RGB-D frame messages.

Wire layout (all integers little-endian), specified for other languages in ``docs/protocol.md``::

    magic   4 bytes  b"OSLM"
    version u16      1
    flags   u16      0 (reserved)
    hlen    u32      length of the JSON header in bytes
    header  hlen     UTF-8 JSON object (see HEADER FIELDS in docs/protocol.md)
    color   header["color"]["size"] bytes   (jpeg | png | rgb8)
    depth   header["depth"]["size"] bytes   (png16 | u16le)
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from graph.geometry import is_rigid, pose_from_tum, pose_to_tum
from perception.frame import CameraModel, Detection, Frame, FrameRejected, Intrinsics, Reason
from perception.image_probe import ProbeError, probe
from service.limits import DEFAULT_LIMITS, Limits

MAGIC = b"OSLM"
VERSION = 1
PREAMBLE = struct.Struct("<4sHHI")
COLOR_ENCODINGS = ("jpeg", "png", "rgb8")
DEPTH_ENCODINGS = ("png16", "u16le")
MAX_DETECTIONS = 512
MAX_HEADER_BYTES = 1 << 20
MAX_JSON_INT = 2**63


# ---------------------------------------------------------------- encoding


def encode_frame(frame: Frame, color_encoding: str = "jpeg", depth_encoding: str = "png16") -> bytes:
    """Serialise a frame as a protocol-v1 message."""
    color = _encode_color(frame.rgb, color_encoding)
    depth = _encode_depth(frame.depth, depth_encoding)
    return frame_head(frame, (color_encoding, len(color)), (depth_encoding, len(depth))) + color + depth


def frame_head(frame: Frame, color: tuple[str, int], depth: tuple[str, int]) -> bytes:
    """A protocol-v1 message up to its images: preamble and header, with the images' (encoding, size)."""
    h, w = frame.depth.shape
    header: dict[str, Any] = {
        "version": VERSION,
        "timestamp": frame.timestamp,
        "seq": frame.seq,
        "frame_id": frame.frame_id,
        "camera": camera_to_json(frame.camera),
        "color": {"encoding": color[0], "width": frame.rgb.shape[1], "height": frame.rgb.shape[0], "size": color[1]},
        "depth": {"encoding": depth[0], "width": w, "height": h, "size": depth[1]},
        "odometry": None if frame.odometry is None else [float(v) for v in pose_to_tum(frame.odometry)],
        "detections": None
        if frame.detections is None
        else [{"label": d.label, "score": float(d.score), "box": [float(v) for v in d.box]} for d in frame.detections],
    }
    head = json.dumps(header, separators=(",", ":")).encode()
    return PREAMBLE.pack(MAGIC, VERSION, 0, len(head)) + head


def camera_to_json(camera: CameraModel) -> dict[str, Any]:
    """The ``camera`` header object."""
    c = camera.color
    out: dict[str, Any] = {
        "fx": c.fx,
        "fy": c.fy,
        "cx": c.cx,
        "cy": c.cy,
        "width": camera.width,
        "height": camera.height,
        "depth_scale": camera.depth_scale,
    }
    if camera.depth_intrinsics is not None:
        d = camera.depth_intrinsics
        out["depth_K"] = {"fx": d.fx, "fy": d.fy, "cx": d.cx, "cy": d.cy}
    if camera.depth_to_color is not None:
        out["depth_to_color"] = np.asarray(camera.depth_to_color, dtype=float).tolist()
    return out


def _encode_color(rgb: np.ndarray, encoding: str) -> bytes:
    if encoding == "rgb8":
        return np.ascontiguousarray(rgb, dtype=np.uint8).tobytes()
    ext = {"jpeg": ".jpg", "png": ".png"}[encoding]
    params = [cv2.IMWRITE_JPEG_QUALITY, 95] if encoding == "jpeg" else []
    ok, buf = cv2.imencode(ext, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), params)
    if not ok:
        raise ValueError(f"could not encode colour as {encoding}")
    return buf.tobytes()


def _encode_depth(depth: np.ndarray, encoding: str) -> bytes:
    depth = np.ascontiguousarray(depth, dtype=np.uint16)
    if encoding == "u16le":
        return depth.astype("<u2").tobytes()
    ok, buf = cv2.imencode(".png", depth, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise ValueError("could not encode depth as png16")
    return buf.tobytes()


# ---------------------------------------------------------------- decoding


@dataclass(frozen=True)
class Inspected:
    """A message whose header, sizes and images' own headers were checked; its pixels are not decoded yet."""

    timestamp: float
    seq: int
    frame_id: str
    camera: CameraModel
    color: memoryview
    color_meta: dict[str, Any]
    depth: memoryview
    depth_meta: dict[str, Any]
    odometry: np.ndarray | None
    detections: list[Detection] | None


def decode_frame(payload: bytes, limits: Limits | None = None) -> Frame:
    """Parse and validate a protocol-v1 message; raises FrameRejected with the first problem found."""
    return decode_images(inspect_message(payload, limits))


def decode_images(message: Inspected) -> Frame:
    """The frame of an inspected message: its colour and depth images decoded (the costly part)."""
    return Frame(
        timestamp=message.timestamp,
        seq=message.seq,
        frame_id=message.frame_id,
        camera=message.camera,
        rgb=_decode_color(message.color, message.color_meta),
        depth=_decode_depth(message.depth, message.depth_meta),
        odometry=message.odometry,
        detections=message.detections,
    )


def inspect_message(payload: bytes, limits: Limits | None = None) -> Inspected:
    """Every check that needs no pixel decoded: preamble, header fields, sizes, and the dimensions the encoded
    images declare in their own headers (``perception.image_probe``), so a decompression bomb is refused unread.
    Cheap enough for zenoh's callback thread; raises FrameRejected with the first problem found."""
    limits = limits or DEFAULT_LIMITS
    if len(payload) > limits.max_payload_bytes:
        raise FrameRejected(Reason.TOO_LARGE, f"{len(payload)} bytes > {limits.max_payload_bytes}")
    header, body = split_message(payload)
    camera = _parse_camera(_field(header, "camera", dict), limits)
    color_meta = _parse_image_meta(_field(header, "color", dict), COLOR_ENCODINGS, "color", limits)
    depth_meta = _parse_image_meta(_field(header, "depth", dict), DEPTH_ENCODINGS, "depth", limits)
    if len(body) != color_meta["size"] + depth_meta["size"]:
        raise FrameRejected(
            Reason.SIZE_MISMATCH,
            f"body has {len(body)} bytes, header declares {color_meta['size'] + depth_meta['size']}",
        )
    if (depth_meta["width"], depth_meta["height"]) != (camera.width, camera.height) and camera.registered:
        raise FrameRejected(Reason.SIZE_MISMATCH, "registered depth must match the camera image size")
    if (color_meta["width"], color_meta["height"]) != (camera.width, camera.height):
        raise FrameRejected(Reason.SIZE_MISMATCH, "colour size differs from camera width/height")
    view = memoryview(body)
    color, depth = view[: color_meta["size"]], view[color_meta["size"] :]
    _check_declared(color, color_meta, "colour", limits)
    _check_declared(depth, depth_meta, "depth", limits)
    return Inspected(
        timestamp=_finite(_field(header, "timestamp", (int, float)), "timestamp"),
        seq=_nonnegative_int(header.get("seq", 0), "seq"),
        frame_id=_short_str(header.get("frame_id", ""), "frame_id", 256),
        camera=camera,
        color=color,
        color_meta=color_meta,
        depth=depth,
        depth_meta=depth_meta,
        odometry=_parse_odometry(header.get("odometry")),
        detections=_parse_detections(header.get("detections"), camera),
    )


def _check_declared(data: memoryview, meta: dict[str, Any], what: str, limits: Limits) -> None:
    """The encoded image's own header agrees with the frame header: its size, and for depth 16-bit gray."""
    encoding = meta["encoding"]
    if encoding in ("rgb8", "u16le"):  # raw: the byte count was checked against width x height
        expected = meta["width"] * meta["height"] * (3 if encoding == "rgb8" else 2)
        if len(data) != expected:
            raise FrameRejected(Reason.SIZE_MISMATCH, f"{encoding} {what} needs {expected} bytes, got {len(data)}")
        return
    try:
        found = probe(data, encoding)
    except ProbeError as exc:
        raise FrameRejected(Reason.BAD_IMAGE, f"{what}: {exc}") from None
    if found.width * found.height > limits.max_image_pixels:
        raise FrameRejected(Reason.TOO_LARGE, f"{what} image declares {found.width}x{found.height} pixels")
    if (found.width, found.height) != (meta["width"], meta["height"]):
        raise FrameRejected(
            Reason.SIZE_MISMATCH,
            f"{what} image declares {found.width}x{found.height}, header {meta['width']}x{meta['height']}",
        )
    if encoding == "png16" and (found.bit_depth != 16 or found.channels != 1):
        raise FrameRejected(Reason.BAD_IMAGE, f"depth is not a single-channel 16-bit PNG ({found})")


def split_message(payload: bytes) -> tuple[dict[str, Any], bytes]:
    """Check the preamble and return the JSON header and the image body."""
    if len(payload) < PREAMBLE.size:
        raise FrameRejected(Reason.TRUNCATED, f"{len(payload)} bytes is shorter than the preamble")
    magic, version, _flags, hlen = PREAMBLE.unpack_from(payload)
    if magic != MAGIC:
        raise FrameRejected(Reason.BAD_MAGIC, f"magic {magic!r} is not {MAGIC!r}")
    if version != VERSION:
        raise FrameRejected(Reason.UNSUPPORTED_VERSION, f"protocol version {version}, this service speaks {VERSION}")
    if hlen > MAX_HEADER_BYTES:
        raise FrameRejected(Reason.BAD_HEADER, f"header length {hlen} exceeds {MAX_HEADER_BYTES}")
    if len(payload) < PREAMBLE.size + hlen:
        raise FrameRejected(Reason.TRUNCATED, "payload ends inside the header")
    try:
        header = json.loads(payload[PREAMBLE.size : PREAMBLE.size + hlen].decode("utf-8"), parse_int=_json_int)
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise FrameRejected(Reason.BAD_HEADER, f"header is not UTF-8 JSON: {exc}") from None
    if not isinstance(header, dict):
        raise FrameRejected(Reason.BAD_HEADER, "header is not a JSON object")
    if header.get("version") != VERSION:
        raise FrameRejected(Reason.UNSUPPORTED_VERSION, f"header version {header.get('version')!r}")
    return header, payload[PREAMBLE.size + hlen :]


def _json_int(text: str) -> int:
    """JSON integers are bounded to 64 bits: a longer literal would overflow float() (or int()) downstream."""
    value = int(text) if len(text) <= 20 else MAX_JSON_INT
    if abs(value) >= MAX_JSON_INT:
        raise FrameRejected(Reason.BAD_HEADER, f"integer {text[:24]} is beyond 64 bits")
    return value


def _field(obj: dict[str, Any], name: str, kind: type | tuple[type, ...]) -> Any:
    if name not in obj:
        raise FrameRejected(Reason.BAD_FIELD, f"missing field {name!r}")
    value = obj[name]
    if isinstance(value, bool) or not isinstance(value, kind):
        raise FrameRejected(Reason.BAD_FIELD, f"field {name!r} has type {type(value).__name__}")
    return value


def _finite(value: float, name: str) -> float:
    value = float(value)
    if not math.isfinite(value):
        raise FrameRejected(Reason.BAD_FIELD, f"{name} is not finite")
    return value


def _nonnegative_int(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0 or value >= 2**63:
        raise FrameRejected(Reason.BAD_FIELD, f"{name} must be a non-negative integer")
    return value


def _short_str(value: Any, name: str, limit: int) -> str:
    if not isinstance(value, str) or len(value) > limit:
        raise FrameRejected(Reason.BAD_FIELD, f"{name} must be a string of at most {limit} characters")
    return value


def _parse_intrinsics(obj: Any, width: int, height: int) -> Intrinsics:
    if not isinstance(obj, dict):
        raise FrameRejected(Reason.BAD_INTRINSICS, "intrinsics must be an object")
    values = []
    for name in ("fx", "fy", "cx", "cy"):
        v = obj.get(name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise FrameRejected(Reason.BAD_INTRINSICS, f"{name} missing or not finite")
        values.append(float(v))
    fx, fy, cx, cy = values
    if not (0 < fx < 100 * width and 0 < fy < 100 * height):
        raise FrameRejected(Reason.BAD_INTRINSICS, f"focal lengths {fx}, {fy} out of range")
    if not (-width < cx < 2 * width and -height < cy < 2 * height):
        raise FrameRejected(Reason.BAD_INTRINSICS, f"principal point {cx}, {cy} out of range")
    return Intrinsics(fx, fy, cx, cy)


def _parse_camera(obj: dict[str, Any], limits: Limits) -> CameraModel:
    width = _field(obj, "width", int)
    height = _field(obj, "height", int)
    if not (width > 0 and height > 0 and width * height <= limits.max_image_pixels):
        raise FrameRejected(Reason.BAD_INTRINSICS, f"image size {width}x{height} out of range")
    color = _parse_intrinsics(obj, width, height)
    scale = obj.get("depth_scale")
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not (math.isfinite(scale) and scale > 0):
        raise FrameRejected(Reason.BAD_INTRINSICS, "depth_scale missing, not finite or not positive")
    depth_k = None if obj.get("depth_K") is None else _parse_intrinsics(obj["depth_K"], width, height)
    extrinsic = None
    if obj.get("depth_to_color") is not None:
        try:
            extrinsic = np.asarray(obj["depth_to_color"], dtype=float)
        except (TypeError, ValueError):
            raise FrameRejected(Reason.BAD_POSE, "depth_to_color is not a 4x4 number matrix") from None
        if not is_rigid(extrinsic):
            raise FrameRejected(Reason.BAD_POSE, "depth_to_color is not a rigid 4x4 transform")
    return CameraModel(color, width, height, float(scale), depth_k, extrinsic)


def _parse_image_meta(obj: dict[str, Any], encodings: tuple[str, ...], what: str, limits: Limits) -> dict[str, Any]:
    encoding = obj.get("encoding")
    if encoding not in encodings:
        raise FrameRejected(Reason.BAD_FIELD, f"{what} encoding {encoding!r} not in {encodings}")
    meta = {"encoding": encoding}
    for name in ("width", "height", "size"):
        v = obj.get(name)
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise FrameRejected(Reason.BAD_FIELD, f"{what}.{name} must be a positive integer")
        meta[name] = v
    if meta["width"] * meta["height"] > limits.max_image_pixels:
        raise FrameRejected(Reason.TOO_LARGE, f"{what} image {meta['width']}x{meta['height']} too large")
    return meta


def _decode_color(data: bytes | memoryview, meta: dict[str, Any]) -> np.ndarray:
    h, w = meta["height"], meta["width"]
    if meta["encoding"] == "rgb8":
        if len(data) != h * w * 3:
            raise FrameRejected(Reason.SIZE_MISMATCH, f"rgb8 needs {h * w * 3} bytes, got {len(data)}")
        return np.frombuffer(data, dtype=np.uint8).reshape(h, w, 3).copy()
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise FrameRejected(Reason.BAD_IMAGE, f"colour is not a decodable {meta['encoding']} image")
    if img.shape[:2] != (h, w):
        raise FrameRejected(Reason.SIZE_MISMATCH, f"colour image is {img.shape[1]}x{img.shape[0]}, header {w}x{h}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _decode_depth(data: bytes | memoryview, meta: dict[str, Any]) -> np.ndarray:
    h, w = meta["height"], meta["width"]
    if meta["encoding"] == "u16le":
        if len(data) != h * w * 2:
            raise FrameRejected(Reason.SIZE_MISMATCH, f"u16le depth needs {h * w * 2} bytes, got {len(data)}")
        return np.frombuffer(data, dtype="<u2").reshape(h, w).astype(np.uint16)
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.dtype != np.uint16 or img.ndim != 2:
        raise FrameRejected(Reason.BAD_IMAGE, "depth is not a single-channel 16-bit PNG")
    if img.shape != (h, w):
        raise FrameRejected(Reason.SIZE_MISMATCH, f"depth image is {img.shape[1]}x{img.shape[0]}, header {w}x{h}")
    return img


def _parse_odometry(value: Any) -> np.ndarray | None:
    if value is None:
        return None
    if not isinstance(value, list) or len(value) != 7:
        raise FrameRejected(Reason.BAD_POSE, "odometry must be [tx, ty, tz, qx, qy, qz, qw]")
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value):
        raise FrameRejected(Reason.BAD_POSE, "odometry has a non-finite or non-numeric value")
    q = np.asarray(value[3:], dtype=float)
    if abs(np.linalg.norm(q) - 1.0) > 1e-3:
        raise FrameRejected(Reason.BAD_POSE, f"odometry quaternion norm {np.linalg.norm(q):.4f} is not 1")
    if np.abs(value[:3]).max() > 1e5:
        raise FrameRejected(Reason.BAD_POSE, "odometry translation beyond 100 km")
    return pose_from_tum(np.asarray(value, dtype=float))


def _parse_detections(value: Any, camera: CameraModel) -> list[Detection] | None:
    if value is None:
        return None
    if not isinstance(value, list) or len(value) > MAX_DETECTIONS:
        raise FrameRejected(Reason.BAD_DETECTIONS, f"detections must be a list of at most {MAX_DETECTIONS}")
    out = []
    for i, det in enumerate(value):
        if not isinstance(det, dict):
            raise FrameRejected(Reason.BAD_DETECTIONS, f"detection {i} is not an object")
        label, score, box = det.get("label"), det.get("score"), det.get("box")
        if not isinstance(label, str) or not 0 < len(label) <= 64 or not label.isprintable():
            raise FrameRejected(Reason.BAD_DETECTIONS, f"detection {i}: label must be a non-empty printable string")
        if isinstance(score, bool) or not isinstance(score, (int, float)) or not 0.0 <= score <= 1.0:
            raise FrameRejected(Reason.BAD_DETECTIONS, f"detection {i}: score must lie in [0, 1]")
        out.append(Detection(label, float(score), _parse_box(box, i, camera)))
    return out


def _parse_box(box: Any, i: int, camera: CameraModel) -> tuple[float, float, float, float]:
    if (
        not isinstance(box, list)
        or len(box) != 4
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in box)
    ):
        raise FrameRejected(Reason.BAD_DETECTIONS, f"detection {i}: box must be 4 finite numbers")
    x1, y1, x2, y2 = (float(v) for v in box)
    if not (x1 < x2 and y1 < y2):
        raise FrameRejected(Reason.BAD_DETECTIONS, f"detection {i}: box corners out of order")
    x1, x2 = max(x1, 0.0), min(x2, float(camera.width))
    y1, y2 = max(y1, 0.0), min(y2, float(camera.height))
    if x2 - x1 < 1.0 or y2 - y1 < 1.0:
        raise FrameRejected(Reason.BAD_DETECTIONS, f"detection {i}: box lies outside the image")
    return (x1, y1, x2, y2)
