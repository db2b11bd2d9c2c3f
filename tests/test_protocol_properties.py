"""Property tests of the protocol decoder: any mutation of a valid message decodes or is rejected with a reason."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from service.protocol import FrameRejected, Reason, decode_frame, encode_frame
from tests.conftest import make_frame

VALID = encode_frame(make_frame(), "png")


def _decode_or_reason(payload: bytes) -> Reason | None:
    try:
        decode_frame(payload)
    except FrameRejected as exc:
        return exc.reason
    return None


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.integers(0, len(VALID) - 1), st.integers(0, 255)), min_size=1, max_size=8))
def test_byte_flips_never_escape_as_anything_but_a_rejection(flips):
    payload = bytearray(VALID)
    for pos, value in flips:
        payload[pos] = value
    reason = _decode_or_reason(bytes(payload))
    assert reason is None or isinstance(reason, Reason)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, len(VALID) - 1))
def test_every_truncation_is_rejected(cut):
    assert _decode_or_reason(VALID[:cut]) in (Reason.TRUNCATED, Reason.SIZE_MISMATCH)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=256))
def test_random_bytes_are_rejected(blob):
    assert _decode_or_reason(blob) is not None
