"""An encoded image's dimensions read from its own header (PNG IHDR, JPEG SOF), before anything is decoded.

A few hundred bytes of JPEG or PNG can declare 30000 x 30000 pixels; decoding them first and checking the size
afterwards costs gigabytes and seconds. These readers touch only the header bytes (JPEG: the marker segments
up to the frame header, each skipped by its length), so a message is judged by what it declares.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_GRAY, PNG_RGB, PNG_PALETTE, PNG_GRAY_ALPHA, PNG_RGBA = 0, 2, 3, 4, 6
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_STANDALONE = {0x01, *range(0xD0, 0xD8)}  # TEM and RSTn carry no length
MAX_JPEG_SCANS = 64
"""A progressive JPEG has about 10 scans; thousands of tiny scans make a small file that decodes for seconds."""


class ProbeError(ValueError):
    """The bytes do not start with a well-formed image header."""


@dataclass(frozen=True)
class ImageHeader:
    width: int
    height: int
    channels: int
    bit_depth: int


def probe(data: bytes | memoryview, encoding: str) -> ImageHeader:
    """The header of ``data`` encoded as ``encoding`` (``png``, ``png16`` or ``jpeg``)."""
    if encoding in ("png", "png16"):
        return png_header(data)
    if encoding == "jpeg":
        return jpeg_header(data)
    raise ValueError(f"no header to probe for {encoding}")


def png_header(data: bytes | memoryview) -> ImageHeader:
    """Width, height, channels and bit depth from a PNG's IHDR chunk (which must come first)."""
    head = bytes(data[:33])
    if len(head) < 33 or head[:8] != PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise ProbeError("not a PNG (no signature and IHDR chunk)")
    width, height, bit_depth, color_type = struct.unpack(">IIBB", head[16:26])
    channels = {PNG_GRAY: 1, PNG_RGB: 3, PNG_PALETTE: 1, PNG_GRAY_ALPHA: 2, PNG_RGBA: 4}.get(color_type)
    if channels is None or width == 0 or height == 0:
        raise ProbeError(f"PNG header declares {width}x{height}, colour type {color_type}")
    return ImageHeader(width, height, channels, bit_depth)


def jpeg_header(data: bytes | memoryview) -> ImageHeader:
    """Width, height and components from a JPEG's frame header (SOFn), found by walking the marker segments."""
    view = memoryview(data)
    if bytes(view[:2]) != b"\xff\xd8":
        raise ProbeError("not a JPEG (no SOI marker)")
    pos = 2
    while pos + 4 <= len(view):
        if view[pos] != 0xFF:
            raise ProbeError(f"JPEG marker expected at byte {pos}")
        marker = view[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in _STANDALONE:
            pos += 2
            continue
        (length,) = struct.unpack_from(">H", view, pos + 2)
        if length < 2:
            raise ProbeError(f"JPEG segment length {length} at byte {pos}")
        if marker in _SOF:
            if pos + 2 + length > len(view) or length < 8:
                raise ProbeError("JPEG frame header truncated")
            bits, height, width, components = struct.unpack_from(">BHHB", view, pos + 4)
            if width == 0 or height == 0 or components not in (1, 3, 4):
                raise ProbeError(f"JPEG frame header declares {width}x{height}, {components} components")
            if bytes(view).count(b"\xff\xda") > MAX_JPEG_SCANS:  # SOS markers (0xFF in entropy data is stuffed)
                raise ProbeError(f"JPEG has more than {MAX_JPEG_SCANS} scans")
            return ImageHeader(width, height, components, bits)
        if marker in (0xDA, 0xD9):  # start of scan or end of image before any frame header
            break
        pos += 2 + length
    raise ProbeError("JPEG has no frame header")
