"""A bounded iSAM2 window over the newest keyframes; the whole graph optimised in a child process (SPEC 6.8, 7).

Why: with gtsam 4.3 an iSAM2 update costs time in proportion to the whole graph (the Bayes tree's destructor
walks every clique on each update, and a return to an old place re-eliminates everything from there to the
root), so a long run would stop keeping up with the camera. ``objslam bench isam2`` measures it.

How (the foreground, ``WindowedGraph``):

- **The window** is an iSAM2 (``PoseGraph``) over keyframes ``[start, n)`` and the landmarks they observe.
  Keyframes before ``start`` are *fixed* at their estimate, and each factor linking one to the window becomes
  a unary factor on the window side, conditioning on the fixed past (``graph.window_factors``).
- **Rolling**: when the window holds ``window_keyframes + window_step`` keyframes its oldest ``window_step``
  become fixed and the window is rebuilt from the factor records in one batch update. A landmark no window
  keyframe observes leaves the window at its estimate ("frozen"); a factor on it brings it back with its
  fixed measurements as priors, fused into one beyond ``FUSE_AT`` (a landmark seen on every lap of a long run).
- **The whole graph** gets every factor as plain records, in a child process (``graph.solver_proxy`` starts
  ``python -m graph.solver_child``: nothing shared with the parent; ``graph.solver_messages``) running a full
  ``PoseGraph``. It is asked to solve at each roll (one solve outstanding at a time). The newest estimate
  that has come back replaces the fixed past at the next roll, which rebuilds the window there (keyframes
  added since the solve moved rigidly with the newest solved one); so the window is rebuilt once per
  ``window_step`` keyframes, whatever the loops. A child that dies is restarted and replays the whole history.
- **Flush** (the end of a run) waits for the whole graph's batch optimum and re-anchors the window there;
  **polish** (a pause in a live stream) does the same without waiting.

Per-keyframe work is bounded by the window, not by the map; a loop closure's correction of the whole map arrives
a solve later. Until the first roll the child is never started and the window is the whole graph, update for
update what ``PoseGraph`` does (same factor indices, same estimate), until a flush.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import numpy as np

from graph.books import Books, UpdateResult
from graph.errors import SolverError
from graph.factors import FactorRecord
from graph.keyframes import Keyframes
from graph.landmarks import Landmarks
from graph.pose_graph import PoseGraph
from graph.settings import GraphSettings, with_window
from graph.solver_messages import Replay, Update
from graph.solver_proxy import GlobalSolver
from graph.window_factors import (
    Estimate,
    FactorIndex,
    Localized,
    anchored,
    landmarks_of,
    localize,
    localized_factors,
    window_factors,
)
from graph.window_state import joined, restore_rolled, window_parts

log = logging.getLogger(__name__)

MAX_CHILD_STARTS = 3  # a child that keeps failing is not restarted again


class WindowedGraph(Keyframes, Landmarks):
    """Keyframe poses and landmarks: a bounded iSAM2 window in front, the whole graph solved in a child.

    ``books``: every factor and update in the whole graph's keyframe ids (index = factor index); ``local``: the
    window's iSAM2, in its own ids (keyframe ``start`` is its 0).
    """

    def __init__(self, settings: GraphSettings | None = None):
        settings = GraphSettings() if settings is None else settings
        if settings.window_keyframes < 2 or settings.window_step < 1:
            raise ValueError("the window needs at least 2 keyframes and a step of at least 1")
        self.settings = settings
        self.books = Books()
        self.local = PoseGraph(settings)
        self.start = 0  # first keyframe in the window; the ones before are fixed
        self._to_local: dict[int, int] = {}  # factor index -> the window's factor index
        self._local_pairs: list[tuple[int, int]] = []  # the same, as added (a log: removals are the books')
        self._fused: dict[int, list[int]] = {}  # a window factor standing for several (``localized_factors``)
        self._index = FactorIndex()  # the factors on each keyframe and landmark
        self._fixed = np.zeros((0, 4, 4))  # keyframes before ``start``
        self._frozen: dict[int, np.ndarray] = {}  # landmarks in the graph but not in the window
        self._global: GlobalSolver | None = None
        self.child_starts = 0  # whole-graph child processes started
        self.global_solves = 0  # global estimates applied to the window
        self.rebuilt = False  # until the window is first rebuilt it is the whole graph, update for update
        self._polish_asked: tuple[int, int] | None = None  # (factors, removals) at ``polish``'s last request
        self._polished: tuple[int, int] | None = None  # (factors, removals) at its last re-anchoring

    # ------------------------------------------------------------ solver

    @property
    def factorization(self) -> str:
        return self.local.factorization

    @property
    def timings(self) -> list[float] | None:
        """Seconds of each ISAM2.update call of the window (rebuilds included), when set to a list."""
        return self.local.timings

    @timings.setter
    def timings(self, value: list[float] | None) -> None:
        self.local.timings = value

    @property
    def child(self) -> GlobalSolver | None:
        """The whole-graph child process (its parent side), None while none runs (before the first roll)."""
        return self._global

    # ------------------------------------------------------------ queries

    def pose(self, k: int) -> np.ndarray:
        if not 0 <= k < self.num_keyframes:
            raise IndexError(f"keyframe {k} is not in the graph")
        return self._fixed[k].copy() if k < self.start else self.local.pose(k - self.start)

    def poses(self) -> np.ndarray:
        return np.concatenate([self._fixed, self.local.poses()]) if self.start else self.local.poses()

    def marginal_covariance(self, k: int) -> np.ndarray:
        """6x6 marginal covariance of a keyframe in the window (the window's, conditioned on the fixed past)."""
        if k < self.start:
            raise ValueError(f"keyframe {k} is fixed (before the window at {self.start})")
        return self.local.marginal_covariance(k - self.start)

    def landmark(self, j: int) -> np.ndarray:
        return self._frozen[j].copy() if j in self._frozen else self.local.landmark(j)

    def landmarks(self) -> dict[int, np.ndarray]:
        return {**self._frozen, **self.local.landmarks()}

    def frozen_landmarks(self) -> dict[int, np.ndarray]:
        """The landmarks in the graph but not in the window (no window keyframe observes them), at their
        estimate when they left it."""
        return {j: p.copy() for j, p in self._frozen.items()}

    def localize(self, f: FactorRecord, landmarks: set[int]) -> FactorRecord | None:
        """A factor (whole-graph ids) in the window's ids; one on a fixed keyframe as a prior on its other end;
        None when nothing of it is in the window (``graph.window_factors.localize``)."""
        return localize(f, self.start, self._fixed, landmarks)

    # ------------------------------------------------------------ the update

    def update(
        self,
        factors: Sequence[FactorRecord],
        poses: Sequence[np.ndarray] = (),
        landmarks: Sequence[tuple[int, np.ndarray]] = (),
        remove: Sequence[int] | None = None,
    ) -> UpdateResult:
        """One update of the window (factors in global ids), recorded and passed on to the whole graph."""
        remove = list(remove or [])
        first, new = len(self.books.factors), {j for j, _ in landmarks}
        local, revived = Localized(), []
        local_landmarks = {j: p for j, p in landmarks}
        for j in landmarks_of(factors) - new - self.local.landmarks_in_solver():
            if j in self._frozen:  # back into the window, its measurements from fixed keyframes as priors
                live = [i for i in self._index.on_landmark(j) if i not in self.books.removed]
                self._extend(local, live, {j: self._frozen[j]})
                local_landmarks[j] = self._frozen[j]
                revived.append(j)
        keep = self.local.landmarks_in_solver() | new | set(revived)
        for i, f in enumerate(factors, start=first):
            r = self.localize(f, keep)
            if r is not None:
                local.add(r, [i])
        local_remove, gone = sorted({self._to_local[i] for i in remove if i in self._to_local}), set(remove)
        for li in local_remove:  # a fused prior goes whole; what is left of it comes back
            if rest := [i for i in self._fused.pop(li, []) if i not in gone]:
                j = int(self.books.factors[rest[0]].b)  # type: ignore[arg-type]  # a landmark measurement's
                self._extend(local, rest, {j: self.local.landmark(j)})
        result = self.local.update(
            local.factors, [np.asarray(p, float) for p in poses], list(local_landmarks.items()), local_remove
        )
        self._own(local.owners, result.factor_indices)
        for i in remove:
            self._to_local.pop(i, None)
        for j in revived:
            del self._frozen[j]
        self._record(factors, poses, landmarks, remove)
        if self._global is not None and (factors or poses or remove):
            self._global.send(
                Update(list(factors), [np.asarray(p, float) for p in poses], list(landmarks), remove, first)
            )
        if self.num_keyframes - self.start >= self.settings.window_keyframes + self.settings.window_step:
            self._roll()
        return UpdateResult(tuple(range(first, first + len(factors))))

    def _extend(self, local: Localized, indices: list[int], landmarks: dict[int, np.ndarray]) -> None:
        """Append the window's factors for ``indices`` on ``landmarks`` and their owners (``localized_factors``)."""
        factors, kept = self.books.factors, set(landmarks)
        given = ((i, factors[i], r) for i in indices if (r := self.localize(factors[i], kept)) is not None)
        localized_factors(given, landmarks, local)

    def _own(self, owners: list[list[int]], indices: Sequence[int]) -> None:
        """Window factors ``indices`` added for the whole-graph ``owners`` of each."""
        for members, li in zip(owners, indices, strict=True):
            for i in members:
                self._to_local[i] = li
                self._local_pairs.append((i, li))
            if len(members) > 1:
                self._fused[li] = members

    def _record(
        self,
        factors: Sequence[FactorRecord],
        poses: Sequence[np.ndarray],
        landmarks: Sequence[tuple[int, np.ndarray]],
        remove: list[int],
    ) -> None:
        self._index.add(factors, len(self.books.factors))
        self.books.record(factors, poses, landmarks, remove)
        if remove:
            self._drop_unconstrained(remove)
        for j in set(self._frozen) - set(self.books.landmarks):  # lost their last factor
            del self._frozen[j]

    def _drop_unconstrained(self, removed: list[int]) -> None:
        books = self.books
        for j in landmarks_of([books.factors[i] for i in removed]) & books.landmarks.keys():
            if all(i in books.removed for i in self._index.on_landmark(j)):
                books.lose_landmark(j)

    # ------------------------------------------------------------ rolling and re-anchoring

    def _roll(self) -> None:
        """Fix the oldest ``window_step`` keyframes and rebuild the window without them, at the whole graph's
        newest estimate when one has come back (else at the current one); then ask for the next solve."""
        child = self._running_child()
        solved = child.receive(0.0) if child is not None else None
        if self._rebuild(self.num_keyframes - self.settings.window_keyframes, *self._anchored(solved)) and solved:
            self.global_solves += 1
        if child is not None:
            child.request()

    def _running_child(self) -> GlobalSolver | None:
        """The whole-graph child, started (again, replaying everything) when it is not running; None once it
        failed ``MAX_CHILD_STARTS`` times: the window then goes on alone, its fixed past as it stands."""
        if self._global is not None and not self._global.dead:
            return self._global
        if self._global is not None:
            log.error("the whole-graph child process stopped (exit code %s)", self._global.exit_code())
            self._global.close()
            self._global = None
        if self.child_starts >= MAX_CHILD_STARTS:
            return None
        self.child_starts += 1
        books = self.books
        try:
            self._global = GlobalSolver(
                Replay(
                    self.settings,
                    list(books.factors),
                    list(books.initial),
                    list(books.landmark_initial),
                    list(books.log),
                )
            )
        except OSError as exc:
            log.error("cannot start the whole-graph child process: %s", exc)
        return self._global

    def _anchored(self, solved: Estimate | None) -> Estimate:
        """Every keyframe and landmark estimate, from a whole-graph solve where it has them (``anchored``)."""
        return anchored(self.poses(), self.landmarks(), solved, self.books.landmarks.keys())

    def _rebuild(self, start: int, estimate: np.ndarray, landmarks: dict[int, np.ndarray]) -> bool:
        """A new window from ``start`` at the given estimate: one batch update of its keyframes and landmarks.
        False (and the window as it was) if iSAM2 rejects it."""
        old = self.start, self._fixed, self.local, self._to_local, self._frozen, self._local_pairs, self._fused
        self.start, self._fixed = start, estimate[:start].copy()
        books = self.books
        indices, kept = window_factors(
            self._index, books.factors, books.removed, books.landmarks.keys(), start, self.num_keyframes
        )
        local = Localized()
        self._extend(local, indices, {j: landmarks[j] for j in kept})
        graph = PoseGraph(self.settings, self.local.factorization)
        graph.timings = self.timings
        try:
            result = graph.update(local.factors, list(estimate[start:]), [(j, landmarks[j]) for j in sorted(kept)])
        except SolverError as exc:
            log.error("rebuilding the iSAM2 window failed, keeping the previous one: %s", exc)
            self.start, self._fixed, self.local, self._to_local, self._frozen, self._local_pairs, self._fused = old
            return False
        self.local, self.rebuilt = graph, True
        self._to_local, self._fused, self._local_pairs = {}, {}, []
        self._own(local.owners, result.factor_indices)
        self._frozen = {j: np.asarray(landmarks[j], float) for j in books.landmarks.keys() - kept}
        return True

    def flush(self, timeout: float = 600.0) -> None:
        """Wait for the batch optimum of everything added so far and re-anchor the window there (e.g. before
        final outputs); between flushes the window is re-anchored at each roll, at iSAM2's newest estimate."""
        if not self.num_keyframes:
            return
        if self.start == 0:  # the window is the whole graph: its own batch optimum
            poses, landmarks = self.local.optimum()
            self._rebuild(0, poses, {**self._frozen, **landmarks})
            return
        child = self._running_child()
        if child is None:
            return
        child.request(exact=True)
        solved = child.receive(timeout)
        if child.outstanding or solved is None:
            log.warning(
                "the whole graph's batch optimum did not come back within %.0f s%s",
                timeout,
                "; re-anchoring at its last estimate" if solved is not None else "",
            )
        if solved is not None and self._rebuild(self.start, *self._anchored(solved)):
            self.global_solves += 1

    def polish(self) -> bool:
        """``flush`` without waiting, once per change of the graph: solved here while the window is the whole
        graph (bounded); after a roll, asked of the child, and the window re-anchored by a later call once it has
        come back. True when the window moved (counted in ``global_solves``)."""
        mark = (len(self.books.factors), len(self.books.removed))
        if not self.num_keyframes or mark == self._polished:
            return False
        estimate: Estimate | None = None
        if self.start == 0:
            poses, landmarks = self.local.optimum()
            estimate = poses, {**self._frozen, **landmarks}
        elif (child := self._running_child()) is not None and mark != self._polish_asked:
            child.request(exact=True)
            self._polish_asked = mark
        elif child is not None and not child.outstanding and (solved := child.receive(0.0)) is not None:
            estimate = self._anchored(solved)
        if estimate is None:
            return False
        self._polished = mark
        moved = self._rebuild(self.start, *estimate)
        self.global_solves += int(moved)
        return moved

    def wait_idle(self, timeout: float = 60.0) -> bool:
        """Wait until the whole-graph child has no solve outstanding (its estimate left for the next take)."""
        return self._global is None or self._global.wait_idle(timeout)

    @property
    def solve_latencies(self) -> list[float]:
        """Seconds from each whole-graph solve request to its estimate's arrival."""
        return [] if self._global is None else list(self._global.latencies)

    def close(self) -> None:
        """Stop the child process (it also ends when this process does: its socket closes)."""
        if self._global is not None:
            self._global.close()
            self._global = None

    # ------------------------------------------------------------ plain state

    def state(self) -> dict[str, Any]:
        """``PoseGraph.state()``'s format (the whole graph's replay log), plus the window: where it starts, the
        landmarks in the solver and the removed factors; once rebuilt, also the fixed keyframes and frozen
        landmarks, the window's own iSAM2 (its ``PoseGraph.state()``, replayed as it is) and which of its
        factors is which (before that the window is the whole graph, replayed from the log). It is
        ``graph.window_state.joined`` of ``parts()``, with the estimates that check a replay."""
        state = joined(*self.parts())
        state["estimate"] = self.poses()
        if self.rebuilt:
            state["window"]["local"]["estimate"] = self.local.poses()
        return state

    def parts(self) -> tuple[dict[str, Any], dict[str, Any]]:
        """``state()`` in two parts (``graph.window_state.window_parts``): what the window bounds, and the
        append-only logs (live)."""
        return window_parts(self)

    @classmethod
    def from_state(cls, state: dict[str, Any], settings: GraphSettings | None = None) -> WindowedGraph:
        """The graph of ``state()`` (or of ``PoseGraph.state()``), its estimate exactly as saved: the window's
        iSAM2 replayed update for update (a window that never rolled is the whole graph), the fixed keyframes
        and frozen landmarks as they were, and the whole graph replayed in a new child. The noise models and
        iSAM2 parameters are the saved ones (the replay needs them); the window's size ``settings``' when
        given (else the saved one, else the default)."""
        saved = state.get("window")
        rebuilt = saved is not None and "local" in saved
        local = PoseGraph.from_state(saved["local"] if saved is not None and rebuilt else state)
        window = settings if settings is not None else (saved["settings"] if saved else GraphSettings())
        graph = cls(with_window(local.settings, window))
        graph.local, graph.rebuilt = local, rebuilt
        if saved is None or not rebuilt:  # the window is the whole graph: its books are the graph's
            graph.books = local.books.copy()
            graph.books.pending, local.books.pending = local.books.pending, {}  # the window's to hold back
            graph._to_local = {i: i for i in range(len(local.factors)) if i not in local.books.removed}
            graph._local_pairs = list(graph._to_local.items())
            graph._index.add(graph.factors, 0)
            return graph
        restore_rolled(graph, state, saved)
        if graph.start:
            graph._running_child()
        return graph
