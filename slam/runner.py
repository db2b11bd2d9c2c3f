"""Where a keyframe's mapping stages run: the core hands them to a runner and takes their results later.

The core is thread-free: it calls ``runner.submit(lane, stage, *args)`` and, at a fixed point, the
handle's ``result()``. ``InlineRunner`` runs each stage at once in the caller's thread; the service's
scheduler (``service.scheduler.ThreadedRunner``) runs them on threads. Because the stages read only what
they are given and their results are applied at the same point, both give bit-identical maps.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from enum import Enum
from typing import Any, Protocol


class Lane(Enum):
    """A sequence of stages that run one at a time, in submission order."""

    DETECT = "detect"  # the ONNX detector (releases the GIL: overlaps the mapping of the keyframe before)
    MAP = "map"  # objects (association, clustering) and loop verification, keyframe by keyframe
    KEYFRAME = "keyframe"  # live: a keyframe's features and factor, beside the tracking of the next frames


class Handle(Protocol):
    """The result of a submitted stage; ``result()`` waits for it and re-raises the stage's exception."""

    def result(self) -> Any: ...

    def done(self) -> bool:
        """The stage has finished (``result()`` would not wait)."""
        ...


def idle(pending: Iterable[dict[str, Handle]]) -> bool:
    """Every stage of ``pending`` (``SlamCore.pending``) has finished: taking the core's state waits for none."""
    return all(handle.done() for jobs in pending for handle in jobs.values())


class Runner(Protocol):
    """Runs stages on lanes."""

    def submit(self, lane: Lane, stage: Callable[..., Any], *args: Any) -> Handle: ...

    def close(self) -> None: ...


class Done:
    """A finished stage: its value, or the exception it raised (re-raised by ``result``)."""

    def __init__(self, value: Any = None, error: BaseException | None = None):
        self._value, self._error = value, error

    def result(self) -> Any:
        if self._error is not None:
            raise self._error
        return self._value

    def done(self) -> bool:
        return True


class InlineRunner:
    """Runs each stage at once in the caller's thread (``run``, tests, benchmarks)."""

    def submit(self, lane: Lane, stage: Callable[..., Any], *args: Any) -> Handle:
        try:
            return Done(stage(*args))
        except Exception as exc:  # handed to whoever takes the result, as a thread would
            return Done(error=exc)

    def close(self) -> None:
        pass
