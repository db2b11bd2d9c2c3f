"""Keyframes made beside the tracking (live): the frame that needs a keyframe is posed by optical flow at once,
and its keyframe (features, the factor's pose refined against the depth, skip edges) is computed on another
thread while the next frames are tracked by flow against the old keyframe.

The front end hands the job to ``submit`` (the core's runner, ``slam.runner.Lane.KEYFRAME``); at each frame it
takes a finished job's keyframe (``Step.deferred``: the core adds it to the graph before the frame), and when
the flow fails it waits for the job first. At most one job is pending: until it is taken the old keyframe stays
the one tracked against, so the job reads a keyframe state nobody changes. A job that found no pose agreeing
with the depth makes no keyframe: the next frame that needs one submits another.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from perception.frame import Frame
from perception.hypotheses import Hypothesis

if TYPE_CHECKING:
    from perception.frontend import VisualOdometry
    from perception.keyframing import Step

log = logging.getLogger(__name__)


class Pending(Protocol):
    """A submitted job (``slam.runner.Handle``)."""

    def result(self) -> Any: ...

    def done(self) -> bool: ...


@dataclass
class Job:
    frame: Frame
    gray: np.ndarray
    handle: Pending
    after: int = 0  # frames tracked since the job's frame


class DeferredKeyframes:
    """The pending keyframe job of a ``VisualOdometry`` (its ``deferral``)."""

    def __init__(self, submit: Callable[..., Pending]):
        self.submit = submit
        self.job: Job | None = None
        self.finished: tuple[Frame, Step] | None = None  # taken while a frame was tracked (``finish``)
        self.submitted = self.failed = 0

    @property
    def pending(self) -> bool:
        return self.job is not None

    def take(self, vo: VisualOdometry, frame: Frame, gray: np.ndarray, flowed: Hypothesis) -> None:
        """``frame`` needs a keyframe: submit its job unless one is pending (the frame is posed by flow)."""
        if self.job is None:
            assert vo._kf_pose is not None
            prior = vo._prediction(frame.timestamp, vo._kf_pose)
            # after = -1: ``count`` counts the job's own frame too
            self.job = Job(frame, gray, self.submit(vo.keyframe_job, frame, gray, flowed, prior), after=-1)
            self.submitted += 1

    def count(self, step: Step) -> None:
        """A frame was tracked while the job is pending."""
        if self.job is not None and step.posed:
            self.job.after += 1

    def ready(self, vo: VisualOdometry) -> None:
        """A finished job's keyframe, made the one tracked against, into ``finished`` (kept there until the
        front end hands it on, so a frame that fails after this does not lose it)."""
        if self.finished is None and self.job is not None and self.job.handle.done():
            self.finished = self._accept(vo, 0)

    def finish(self, vo: VisualOdometry, counted: bool) -> None:
        """Wait for the pending job and take its keyframe (into ``finished``); ``counted``: the frame being
        tracked was already counted in the front end's frames since its keyframe."""
        if self.job is not None and self.finished is None:
            self.finished = self._accept(vo, int(counted))

    def drop(self) -> None:
        """Another source poses the frames now: the pending job is waited for and discarded."""
        if self.job is not None:
            try:
                self.job.handle.result()
            except Exception:
                log.debug("discarded keyframe job failed", exc_info=True)
            self.job = None

    def _accept(self, vo: VisualOdometry, extra: int) -> tuple[Frame, Step] | None:
        job, self.job = self.job, None
        assert job is not None
        try:
            step = job.handle.result()
        except Exception:  # the tracking must survive anything a frame can trigger
            log.exception("making a keyframe failed")
            step = None
        if step is None:
            self.failed += 1
            return None
        vo.accept_keyframe(job.frame, job.gray, step, job.after + extra)
        return job.frame, step
