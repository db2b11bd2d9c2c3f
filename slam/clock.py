"""A stream's time reference: duplicate, out-of-order and implausibly far timestamps are rejected.

One frame stamped far in the future must not become the reference (every later frame of the robot would be
``out_of_order``), so a frame more than ``horizon_s`` after the last accepted one is rejected as ``time_jump``.
A clock that really jumped (a robot's clock set, a long pause) shows as several such frames in a row, each
consistent with the one before: the ``confirm``-th of them becomes the new reference (counted in ``resets``).
A restarted service continues from its map's last timestamp, so a robot that comes back the next morning,
hours later, starts a new time reference after ``confirm`` frames, and a crafted frame stamped far ahead is
no more accepted after a restart than before it.
"""

from __future__ import annotations

from perception.frame import FrameRejected, Reason


class StreamClock:
    """The last accepted timestamp and the run of jumped ones that may replace it."""

    def __init__(self, horizon_s: float, confirm: int):
        self.horizon_s, self.confirm = horizon_s, confirm
        self.reference: float | None = None
        self.resets = 0
        self._run: list[float] = []

    def check(self, t: float, jump_ok: bool = False) -> None:
        """Raise FrameRejected unless ``t`` may follow the reference (``accept`` it once the frame is used).
        ``jump_ok``: any time ahead may (the first frame of a new session of the map)."""
        ref = self.reference
        if ref is None or (jump_ok and t > ref):
            return
        if t == ref:
            raise FrameRejected(Reason.DUPLICATE_TIMESTAMP, f"timestamp {t} already processed")
        if t < ref:
            raise FrameRejected(Reason.OUT_OF_ORDER, f"timestamp {t} < {ref}")
        if t - ref <= self.horizon_s:
            return
        consistent = bool(self._run) and 0 < t - self._run[-1] <= self.horizon_s
        self._run = [*self._run, t] if consistent else [t]
        if len(self._run) < self.confirm:
            raise FrameRejected(
                Reason.TIME_JUMP, f"timestamp {t} is {t - ref:.3g} s after the last frame (horizon {self.horizon_s} s)"
            )
        self.resets += 1

    def accept(self, t: float) -> None:
        """``t`` is the new reference (a frame with it was used)."""
        self.reference = t
        self._run = []

    def state(self) -> dict:
        return {"reference": self.reference, "resets": self.resets}

    def restore(self, state: dict, last: float | None) -> None:
        """Continue after the map's last frame, stamped ``last``."""
        self.resets = state.get("resets", 0)
        self.reference = last
