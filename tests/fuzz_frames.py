"""A seeded storm of protocol-v1 messages for the fuzz test: good frames and each class of bad input.

Every message comes with what the service must do with it: ``"processed"`` or the value of the Reason it
must be rejected with. The expectations follow the protocol (docs/protocol.md) and the stream state (the
last processed timestamp), not the decoder, except for the byte-flip and random-preamble classes, whose
reason is taken from ``decode_frame`` (the service must agree with its own decoder and survive).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable

import cv2
import numpy as np

from service.protocol import MAGIC, PREAMBLE, VERSION, FrameRejected, Reason, decode_frame, encode_frame, split_message
from tests.conftest import make_frame

PROCESSED = "processed"
WIDTH, HEIGHT = 64, 48
Message = tuple[bytes, str]
CLASSES = (
    "good",
    "truncated",
    "random_bytes",
    "random_after_preamble",
    "byte_flips",
    "bad_magic",
    "preamble_version",
    "header_version",
    "header_not_json",
    "header_not_object",
    "header_too_long",
    "huge_integer",
    "missing_field",
    "unknown_encoding",
    "wrong_size",
    "image_too_large",
    "undecodable_image",
    "bad_intrinsics",
    "bad_pose",
    "duplicate_timestamp",
    "out_of_order",
    "time_jump",
    "zero_depth",
    "no_odometry",
    "absurd_box",
    "bad_detection",
    "clipped_huge_box",
    "empty_detections",
    "resolution_change",
    "wild_odometry",
    "odometry_jump",
)


def pack(
    header: dict | bytes, body: bytes, magic: bytes = MAGIC, version: int = VERSION, hlen: int | None = None
) -> bytes:
    """A message from a header (dict, or raw header bytes) and a body; preamble fields may be forged."""
    head = header if isinstance(header, bytes) else json.dumps(header).encode()
    return PREAMBLE.pack(magic, version, 0, len(head) if hlen is None else hlen) + head + body


class Storm:
    """Seeded generator of (payload, expected outcome) pairs; tracks the last processed timestamp."""

    def __init__(self, seed: int):
        self.rng = np.random.default_rng(seed)
        self.t = 0.0  # timestamp of the last frame the service will have processed
        self.seq = 0
        self._bases = [
            split_message(encode_frame(make_frame(seed=k, width=WIDTH, height=HEIGHT), "rgb8", "u16le"))
            for k in range(4)
        ]
        small = make_frame(seed=9, width=WIDTH // 2, height=HEIGHT // 2)
        self._small = split_message(encode_frame(small, "rgb8", "u16le"))
        self.classes: dict[str, Callable[[], Message]] = {name: getattr(self, name) for name in CLASSES}

    # ------------------------------------------------------------ helpers

    def valid(self, advance: bool = True) -> tuple[dict, bytes]:
        """A valid header and body; with ``advance`` its timestamp is after every processed frame."""
        header, body = self._bases[int(self.rng.integers(len(self._bases)))]
        header = json.loads(json.dumps(header))
        t = self.t + 0.05 if advance else self.t
        self.seq += 1
        header.update(timestamp=t, seq=self.seq, odometry=[0.1 * t, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
        return header, body

    def _processed(self, header: dict, body: bytes) -> Message:
        self.t = header["timestamp"]
        return pack(header, body), PROCESSED

    def _pick(self, options: list):
        return options[int(self.rng.integers(len(options)))]

    @staticmethod
    def _oracle(payload: bytes) -> str | None:
        try:
            decode_frame(payload)
        except FrameRejected as exc:
            return exc.reason.value
        return None

    # ------------------------------------------------------------ accepted

    def good(self) -> Message:
        return self._processed(*self.valid())

    def clipped_huge_box(self) -> Message:
        header, body = self.valid()
        header["detections"] = [
            {
                "label": "tv",
                "score": 0.5,
                "box": self._pick([[-1e9, -1e9, 1e9, 1e9], [0, 0, 1e308, 1e308], [-5, -5, 30, 400]]),
            }
        ]
        return self._processed(header, body)

    def empty_detections(self) -> Message:
        header, body = self.valid()
        header["detections"] = []
        return self._processed(header, body)

    def resolution_change(self) -> Message:
        """A valid frame of another size mid-stream (a camera reconfigured): must still be processed."""
        header, body = self._small
        header = json.loads(json.dumps(header))
        t = self.t + 0.05
        header.update(timestamp=t, odometry=[0.1 * t, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], detections=[])
        return self._processed(header, body)

    def wild_odometry(self) -> Message:
        """Valid odometry with a random rotation and a jump of up to 0.9 m: within what a frame may move."""
        header, body = self.valid()
        q = self.rng.normal(size=4)
        offset = self.rng.normal(size=3)
        offset *= self.rng.uniform(0.0, 0.9) / np.linalg.norm(offset)
        header["odometry"] = [*(np.array(header["odometry"][:3]) + offset).tolist(), *(q / np.linalg.norm(q)).tolist()]
        return self._processed(header, body)

    def odometry_jump(self) -> Message:
        """Odometry 10 m to 10 km away from the last processed frame's (a glitch): rejected, never in the graph."""
        header, body = self.valid()
        direction = self.rng.normal(size=3)
        offset = direction / np.linalg.norm(direction) * 10.0 ** self.rng.uniform(1.0, 4.0)
        header["odometry"][:3] = (np.array(header["odometry"][:3]) + offset).tolist()
        return pack(header, body), Reason.ODOMETRY_JUMP.value

    # ------------------------------------------------------------ preamble and framing

    def truncated(self) -> Message:
        header, body = self.valid()
        payload = pack(header, body)
        cut = int(self.rng.integers(0, len(payload)))
        head_end = PREAMBLE.size + len(json.dumps(header).encode())
        return payload[:cut], (Reason.TRUNCATED if cut < head_end else Reason.SIZE_MISMATCH).value

    def random_bytes(self) -> Message:
        n = int(self.rng.integers(0, 64)) if self.rng.random() < 0.5 else int(self.rng.integers(64, 20000))
        blob = self.rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        if blob[:4] == MAGIC:  # 2^-32: keep the expectation simple
            blob = b"X" + blob[1:]
        return blob, (Reason.TRUNCATED if n < PREAMBLE.size else Reason.BAD_MAGIC).value

    def random_after_preamble(self) -> Message:
        while True:
            tail = self.rng.integers(0, 256, int(self.rng.integers(0, 4000)), dtype=np.uint8).tobytes()
            payload = PREAMBLE.pack(MAGIC, VERSION, 0, int(self.rng.integers(0, 2 * len(tail) + 2))) + tail
            reason = self._oracle(payload)
            if reason is not None:
                return payload, reason

    def byte_flips(self) -> Message:
        """1-8 random bytes of the preamble and header overwritten; only messages the decoder rejects."""
        header, body = self.valid()
        payload = bytearray(pack(header, body))
        end = PREAMBLE.size + len(json.dumps(header).encode())
        while True:
            for pos in self.rng.integers(0, end, int(self.rng.integers(1, 9))):
                payload[pos] = int(self.rng.integers(0, 256))
            reason = self._oracle(bytes(payload))
            if reason is not None:
                return bytes(payload), reason

    def bad_magic(self) -> Message:
        header, body = self.valid()
        return pack(header, body, magic=self._pick([b"OSLN", b"\0\0\0\0", b"oslm", b"MLSO"])), Reason.BAD_MAGIC.value

    def preamble_version(self) -> Message:
        header, body = self.valid()
        return pack(header, body, version=self._pick([0, 2, 255, 65535])), Reason.UNSUPPORTED_VERSION.value

    def header_version(self) -> Message:
        header, body = self.valid()
        header["version"] = self._pick([0, 2, "1", None, 1.5, [1]])
        return pack(header, body), Reason.UNSUPPORTED_VERSION.value

    # ------------------------------------------------------------ header

    def header_not_json(self) -> Message:
        header, body = self.valid()
        head = json.dumps(header).encode()
        broken = self._pick(
            [
                head[: int(self.rng.integers(1, len(head)))],  # a strict prefix of an object
                b"\xff\xfe" + head,
                head.replace(b":", b"=", 1),
                b"{" * 50_000,
            ]
        )
        return pack(broken, body), Reason.BAD_HEADER.value

    def header_not_object(self) -> Message:
        _, body = self.valid()
        return pack(self._pick([b"[1, 2]", b"42", b"null", b'"OSLM"']), body), Reason.BAD_HEADER.value

    def header_too_long(self) -> Message:
        header, body = self.valid()
        return pack(header, body, hlen=(1 << 20) + int(self.rng.integers(1, 1 << 30))), Reason.BAD_HEADER.value

    def huge_integer(self) -> Message:
        header, body = self.valid()
        big = int(self.rng.integers(19, 400))
        value = 10**big
        edit = self._pick(
            [
                lambda: header.update(timestamp=value),
                lambda: header["camera"].update(fx=value),
                lambda: header.update(seq=value),
                lambda: header["odometry"].__setitem__(0, -value),
            ]
        )
        edit()
        return pack(header, body), Reason.BAD_HEADER.value

    def missing_field(self) -> Message:
        header, body = self.valid()
        name = self._pick(["timestamp", "camera", "color", "depth"])
        if self.rng.random() < 0.5:
            del header[name]
        else:
            header[name] = self._pick(["x", True, None, [], {}] if name == "timestamp" else ["x", 1, [], True])
        return pack(header, body), Reason.BAD_FIELD.value

    def unknown_encoding(self) -> Message:
        header, body = self.valid()
        part = self._pick(["color", "depth"])
        header[part]["encoding"] = self._pick(["bmp", "png8", "u16be", "", None, 7, "RGB8"])
        return pack(header, body), Reason.BAD_FIELD.value

    def wrong_size(self) -> Message:
        header, body = self.valid()
        kind = int(self.rng.integers(4))
        if kind == 0:  # camera size disagrees with the images
            header["camera"]["width"] += int(self.rng.integers(1, 50))
        elif kind == 1:  # colour header size disagrees with the camera (bytes still add up)
            header["color"]["height"] -= 1
            header["color"]["size"] -= WIDTH * 3
            header["depth"]["size"] += WIDTH * 3
        elif kind == 2:  # declared sizes disagree with the body
            header["depth"]["size"] += int(self.rng.integers(1, 100))
        else:  # extra bytes after the images
            body = body + self.rng.integers(0, 256, int(self.rng.integers(1, 100)), dtype=np.uint8).tobytes()
        return pack(header, body), Reason.SIZE_MISMATCH.value

    def image_too_large(self) -> Message:
        header, body = self.valid()
        header[self._pick(["color", "depth"])].update(width=100_000, height=100_000)
        return pack(header, body), Reason.TOO_LARGE.value

    def undecodable_image(self) -> Message:
        """Raw pixels declared as an image file, or an 8-bit PNG as depth."""
        header, body = self.valid()
        kind = int(self.rng.integers(3))
        if kind == 0:
            header["color"]["encoding"] = self._pick(["png", "jpeg"])
        elif kind == 1:
            header["depth"]["encoding"] = "png16"
        else:
            _, png8 = cv2.imencode(".png", np.full((HEIGHT, WIDTH), 100, np.uint8))
            header["depth"].update(encoding="png16", size=len(png8))
            body = body[: header["color"]["size"]] + png8.tobytes()
        return pack(header, body), Reason.BAD_IMAGE.value

    def bad_intrinsics(self) -> Message:
        header, body = self.valid()
        name, value = self._pick(
            [
                ("fx", math.nan),
                ("fy", math.inf),
                ("cx", -math.inf),
                ("fx", 0.0),
                ("fy", -50.0),
                ("fx", 1e12),
                ("cx", 1e6),
                ("cy", -1e6),
                ("depth_scale", 0.0),
                ("depth_scale", math.nan),
                ("depth_scale", -1000.0),
                ("width", 0),
                ("height", -48),
                ("fx", "50"),
                ("fy", None),
                ("depth_scale", True),
            ]
        )
        header["camera"][name] = value
        return pack(header, body), Reason.BAD_INTRINSICS.value

    def bad_pose(self) -> Message:
        header, body = self.valid()
        odometry = header["odometry"]
        header["odometry"] = self._pick(
            [
                [math.nan, *odometry[1:]],
                [*odometry[:3], math.inf, 0.0, 0.0, 1.0],
                odometry[:6],
                [*odometry, 1.0],
                [*odometry[:6], 2.0],
                [*odometry[:3], 0.0, 0.0, 0.0, 0.0],
                [1e9, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
                "identity",
                {"x": 0},
                [*odometry[:6], True],
            ]
        )
        return pack(header, body), Reason.BAD_POSE.value

    # ------------------------------------------------------------ stream state

    def duplicate_timestamp(self) -> Message:
        return pack(*self.valid(advance=False)), Reason.DUPLICATE_TIMESTAMP.value

    def out_of_order(self) -> Message:
        header, body = self.valid()
        header["timestamp"] = self.t - float(self.rng.uniform(1e-6, max(self.t, 1e-6)))
        return pack(header, body), Reason.OUT_OF_ORDER.value

    def time_jump(self) -> Message:
        header, body = self.valid(advance=False)
        header["timestamp"] = self.t + float(self.rng.uniform(1e3, 1e15))  # never becomes the reference
        return pack(header, body), Reason.TIME_JUMP.value

    def zero_depth(self) -> Message:
        header, body = self.valid()
        color_size = header["color"]["size"]
        return pack(header, body[:color_size] + bytes(len(body) - color_size)), Reason.EMPTY_DEPTH.value

    def no_odometry(self) -> Message:
        header, body = self.valid()
        if self.rng.random() < 0.5:
            del header["odometry"]
        else:
            header["odometry"] = None
        return pack(header, body), Reason.NO_ODOMETRY.value

    # ------------------------------------------------------------ detections

    def absurd_box(self) -> Message:
        header, body = self.valid()
        box = self._pick(
            [
                [math.nan, 0, 10, 10],
                [0, 0, math.inf, 10],
                [-100, -100, -10, -10],  # NaN, inf, outside
                [20, 20, 10, 10],
                [5, 5, 5, 30],
                [1e9, 1e9, 2e9, 2e9],
                [0, 0, 0.5, 0.5],  # inverted, empty
                [1, 2, 3],
                "box",
                [1, 2, 3, "4"],
                None,
            ]
        )
        header["detections"] = [{"label": "cup", "score": 0.9, "box": box}]
        return pack(header, body), Reason.BAD_DETECTIONS.value

    def bad_detection(self) -> Message:
        header, body = self.valid()
        good = {"label": "cup", "score": 0.9, "box": [5, 6, 20, 30]}
        header["detections"] = self._pick(
            [
                [{**good, "score": math.nan}],
                [{**good, "score": 1.5}],
                [{**good, "score": -0.1}],
                [{**good, "label": ""}],
                [{**good, "label": 3}],
                [{**good, "label": "x" * 65}],
                ["cup"],
                "cup",
                [good] * 513,
                {"label": "cup"},
            ]
        )
        return pack(header, body), Reason.BAD_DETECTIONS.value
