"""Crafted messages for ``objslam bench hostile``: decompression bombs, garbage, label floods, poisoned stamps."""

from __future__ import annotations

import json
import struct
import tempfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from perception.frame import CameraModel, Frame, Intrinsics
from service.protocol import MAGIC, MAX_DETECTIONS, PREAMBLE, VERSION, encode_frame, split_message

ROBOT = "hostile"
PREFIX = f"objslam/{ROBOT}"
STATUS_KEY = f"{PREFIX}/status"
DATASET = "synthetic:room?seed=0&frames=300"
CAMERA_HZ = 30.0
WARMUP_FRAMES = 30
BOMB_SIDE = 30_000
BOMB_EVERY_S = 3.0
SMALL_W, SMALL_H = 64, 48
GARBAGE_RATE_HZ = 10 * CAMERA_HZ
JUNK_BYTES, JUNK_EVERY_S = 60 * 2**20, 0.1
LABEL_FRAMES = 60
QUERY_RATE_HZ, QUERY_TIMEOUT_S, QUERY_FRAMES = 500.0, 10.0, 300
SAVE_RATE_HZ, SAVE_FRAMES = 20.0, 90
POISON_STAMP = 1e15
RSS_TARGET_MB, RECOVERY_TARGET_S, GARBAGE_PROCESSED_TARGET, INGEST_P99_FACTOR = 100.0, 1.0, 95.0, 2.0
ATTACKS = (
    "quiet",
    "jpeg_bomb",
    "png_bomb",
    "garbage_flood",
    "junk_60mb",
    "label_flood",
    "query_flood",
    "save_flood",
    "time_poison",
)

# ---------------------------------------------------------------- crafted messages


def pack(header: dict[str, Any], body: bytes, magic: bytes = MAGIC) -> bytes:
    """A protocol-v1 message: preamble, JSON header, image bytes."""
    head = json.dumps(header, separators=(",", ":")).encode()
    return PREAMBLE.pack(magic, VERSION, 0, len(head)) + head + body


def restamped(payload: bytes, **fields: Any) -> bytes:
    """``payload`` with header fields replaced (timestamp, detections, ...)."""
    header, body = split_message(payload)
    return pack({**header, **fields}, body)


def small_frame(timestamp: float) -> tuple[dict[str, Any], bytes, bytes]:
    """The header, JPEG colour and 16-bit PNG depth of a valid 64x48 frame (depth 1 m, no detections)."""
    yy, xx = np.mgrid[0:SMALL_H, 0:SMALL_W]
    rgb = np.stack([xx * 4, yy * 5, (xx + yy) * 2], axis=-1).astype(np.uint8)
    camera = CameraModel(Intrinsics(50.0, 50.0, SMALL_W / 2, SMALL_H / 2), SMALL_W, SMALL_H, 5000.0)
    depth = np.full((SMALL_H, SMALL_W), 5000, np.uint16)
    header, body = split_message(encode_frame(Frame(timestamp, 0, "hostile", camera, rgb, depth, None, [])))
    color_size = header["color"]["size"]
    return header, body[:color_size], body[color_size:]


def carrier(timestamp: float, color: bytes | None = None, depth: bytes | None = None) -> bytes:
    """A small valid frame whose colour or depth bytes are replaced; the header keeps claiming 64x48."""
    header, small_color, small_depth = small_frame(timestamp)
    color, depth = color or small_color, depth or small_depth
    header["color"]["size"], header["depth"]["size"] = len(color), len(depth)
    return pack(header, color + depth)


def sof_offset(jpeg: bytes | bytearray) -> int:
    """Offset of the JPEG's frame header marker (SOFn), found by walking the marker segments."""
    pos = 2
    while pos + 4 <= len(jpeg):
        marker = jpeg[pos + 1]
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            return pos
        pos += 2 + struct.unpack_from(">H", jpeg, pos + 2)[0]
    raise ValueError("no SOF marker")


def jpeg_bomb_image(side: int = BOMB_SIDE) -> bytes:
    """The small frame's JPEG (about 1 KB) with its SOF patched to declare ``side`` x ``side`` pixels."""
    data = bytearray(small_frame(0.0)[1])
    struct.pack_into(">HH", data, sof_offset(data) + 5, side, side)  # after length (2) and precision (1)
    return bytes(data)


def png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def png_bomb(width: int = BOMB_SIDE, height: int = BOMB_SIDE) -> bytes:
    """A 16-bit grayscale PNG of zeros that genuinely decodes to ``width`` x ``height`` (1.8 GB for 30000^2).

    Each row is filter byte 0 and 2 x width zero bytes. A block of rows is deflated once, alone and
    byte-aligned (sync flush), and repeated: its back-references stay inside it, so the concatenation is a valid
    deflate stream. The zlib trailer is the Adler-32 of n zero bytes, (n mod 65521) << 16 | 1."""
    rows = next(r for r in (100, 50, 25, 20, 10, 5, 4, 2, 1) if height % r == 0)
    block = bytes((1 + 2 * width) * rows)
    deflate = zlib.compressobj(9, zlib.DEFLATED, -15)
    body = deflate.compress(block) + deflate.flush(zlib.Z_SYNC_FLUSH)
    final = zlib.compressobj(9, zlib.DEFLATED, -15).flush()  # an empty final block
    raw = len(block) * (height // rows)
    idat = zlib.compress(b"", 9)[:2] + body * (height // rows) + final + struct.pack(">I", (raw % 65521) << 16 | 1)
    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)  # 16-bit gray, deflate, filter 0, no interlace
    return b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", ihdr) + png_chunk(b"IDAT", idat) + png_chunk(b"IEND", b"")


def cached_png_bomb() -> bytes:
    """The 30000 x 30000 PNG bomb, built once and kept under the temporary directory."""
    path = Path(tempfile.gettempdir()) / f"objslam-png-bomb-{BOMB_SIDE}.png"
    if path.is_file():
        return path.read_bytes()
    data = png_bomb()
    path.write_bytes(data)
    return data


def garbage(rng: np.random.Generator, good: bytes, count: int = 64) -> list[bytes]:
    """Half random byte strings (12 B to 64 KB), half a good frame with a bad magic."""
    bad_magic = b"XSLM" + good[4:]
    return [bad_magic if i % 2 else rng.bytes(int(rng.integers(12, 65536))) for i in range(count)]


def flood_detections(rng: np.random.Generator, width: int, height: int, count: int = MAX_DETECTIONS) -> list[dict]:
    """``count`` valid detections, each with a fresh random label."""
    x1, y1 = rng.uniform(0, width - 20, count), rng.uniform(0, height - 20, count)
    x2 = np.minimum(x1 + rng.uniform(8, 160, count), width)
    y2 = np.minimum(y1 + rng.uniform(8, 160, count), height)
    labels, scores = rng.integers(0, 2**62, count), rng.uniform(0.3, 1.0, count)
    return [
        {"label": f"flood-{label:016x}", "score": float(s), "box": [float(a), float(b), float(c), float(d)]}
        for label, s, a, b, c, d in zip(labels, scores, x1, y1, x2, y2, strict=True)
    ]
