"""The crafted messages of ``objslam bench hostile`` are what they claim (no service started)."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest

from bench import attacks as hostile
from perception.frame import FrameRejected, Reason
from perception.image_probe import probe
from service.protocol import MAX_DETECTIONS, decode_frame, encode_frame, inspect_message, split_message
from tests.conftest import make_frame


def _chunks(png: bytes) -> list[tuple[bytes, bytes, int]]:
    """(type, data, stored CRC) of each chunk after the signature."""
    out, pos = [], 8
    while pos < len(png):
        (length,) = struct.unpack_from(">I", png, pos)
        kind, data = png[pos + 4 : pos + 8], png[pos + 8 : pos + 8 + length]
        out.append((kind, data, struct.unpack_from(">I", png, pos + 8 + length)[0]))
        pos += 12 + length
    return out


def test_the_carrier_frame_alone_is_a_valid_64x48_frame():
    frame = decode_frame(hostile.carrier(2.5))
    assert (frame.camera.width, frame.camera.height, frame.timestamp) == (64, 48, 2.5)
    assert frame.depth.shape == (48, 64) and int(frame.depth.min()) == 5000


def test_jpeg_bomb_is_about_a_kilobyte_and_its_sof_declares_30000_square():
    jpeg = hostile.jpeg_bomb_image()
    assert 500 < len(jpeg) < 2048
    found = probe(jpeg, "jpeg")
    assert (found.width, found.height, found.channels) == (30000, 30000, 3)
    payload = hostile.carrier(1.0, color=jpeg)
    header, _ = split_message(payload)
    assert (header["color"]["width"], header["color"]["height"], header["color"]["size"]) == (64, 48, len(jpeg))
    with pytest.raises(FrameRejected) as exc:
        inspect_message(payload)
    assert exc.value.reason is Reason.TOO_LARGE


def test_png_bomb_ihdr_declares_30000_square_16_bit_gray_and_every_crc_matches():
    png = hostile.png_bomb()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    chunks = _chunks(png)
    assert [kind for kind, _, _ in chunks] == [b"IHDR", b"IDAT", b"IEND"]
    assert all(zlib.crc32(kind + data) == crc for kind, data, crc in chunks)
    assert struct.unpack(">IIBBBBB", chunks[0][1]) == (30000, 30000, 16, 0, 0, 0, 0)
    assert 1.5 * 2**20 < len(png) < 2.0 * 2**20
    # the first 100 rows inflate to filter byte 0 and 60000 zero bytes each
    rows = zlib.decompressobj().decompress(chunks[1][1], 100 * 60001)
    assert len(rows) == 100 * 60001 and not any(rows)
    payload = hostile.carrier(1.0, depth=png)
    assert split_message(payload)[0]["depth"] == {"encoding": "png16", "width": 64, "height": 48, "size": len(png)}
    with pytest.raises(FrameRejected) as exc:
        inspect_message(payload)
    assert exc.value.reason is Reason.TOO_LARGE


def test_a_small_png_bomb_built_the_same_way_decodes_to_its_declared_size():
    png = hostile.png_bomb(300, 200)
    idat = _chunks(png)[1][1]
    assert len(zlib.decompress(idat)) == 200 * (1 + 2 * 300)  # the Adler-32 trailer is checked too
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image.shape == (200, 300) and image.dtype == np.uint16 and not image.any()


def test_the_png_bomb_is_cached_once(tmp_path, monkeypatch):
    monkeypatch.setattr(hostile.tempfile, "gettempdir", lambda: str(tmp_path))
    built = hostile.cached_png_bomb()
    assert (tmp_path / "objslam-png-bomb-30000.png").read_bytes() == built == hostile.cached_png_bomb()


def test_garbage_is_refused_before_anything_is_decoded():
    good = encode_frame(make_frame())
    messages = hostile.garbage(np.random.default_rng(0), good, count=16)
    reasons = set()
    for message in messages:
        with pytest.raises(FrameRejected) as exc:
            inspect_message(message)
        reasons.add(exc.value.reason)
    assert reasons == {Reason.BAD_MAGIC}
    assert sum(m[4:] == good[4:] for m in messages) == 8


def test_label_flood_frame_carries_512_valid_detections_with_distinct_labels():
    payload = hostile.restamped(
        encode_frame(make_frame()), detections=hostile.flood_detections(np.random.default_rng(0), 64, 48)
    )
    message = inspect_message(payload)
    assert message.detections is not None and len(message.detections) == MAX_DETECTIONS
    assert len({d.label for d in message.detections}) == MAX_DETECTIONS


def test_the_poisoned_frame_is_valid_and_stamped_1e15():
    payload = hostile.restamped(encode_frame(make_frame()), timestamp=hostile.POISON_STAMP)
    assert inspect_message(payload).timestamp == 1e15
