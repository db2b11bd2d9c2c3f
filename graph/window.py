"""A bounded iSAM2 window over the newest keyframes; the whole graph optimised in a child process (SPEC 6.8, 7).

Why: with gtsam 4.3 an iSAM2 update costs time in proportion to the whole graph (the Bayes tree's destructor
walks every clique on each update, and a return to an old place re-eliminates everything from there to the
root), so a long run would stop keeping up with the camera. ``objslam bench isam2`` measures it.

How (the foreground, ``WindowedGraph``):

- **The window** is an iSAM2 (``PoseGraph``) over keyframes ``[start, n)`` and the landmarks they observe.
  Keyframes before ``start`` are *fixed* at their estimate, and each factor linking one to the window becomes
  a unary factor on the window side, conditioning on the fixed past: a between-factor a -> b with ``a`` fixed
  is a prior ``T_a @ T_ab`` on ``b`` with the same noise and kernel, with ``b`` fixed a prior ``T_b @ T_ab^-1``
  on ``a`` whose covariance is carried through ``Ad(T_ab)`` (both exact); a landmark measured from a fixed
  keyframe is a world-position prior on the landmark with the measurement's covariance rotated into the world
  (to first order the bearing-range factor's: isotropic, or wider along the viewing ray).
- **Rolling**: when the window holds ``window_keyframes + window_step`` keyframes its oldest ``window_step``
  become fixed and the window is rebuilt from the factor records in one batch update. A landmark no window
  keyframe observes leaves the window at its estimate ("frozen"); a factor on it brings it back with its
  fixed measurements as priors.
- **The whole graph** gets every factor as plain records, in a child process (``python -m graph.window``:
  nothing shared with the parent) running a full ``PoseGraph``. It is asked to solve at each roll (one solve
  outstanding at a time). The newest estimate that has come back replaces the fixed past at the next roll,
  which rebuilds the window there (keyframes added since the solve moved rigidly with the newest solved one);
  so the window is rebuilt once per ``window_step`` keyframes, whatever the loops. A child that dies is
  restarted and replays the whole history.
- **Flush** (the end of a run) waits for the whole graph's batch optimum and re-anchors the window there.

Per-keyframe work is bounded by the window, not by the map; a loop closure's correction of the whole map
arrives a solve later. Until the first roll the child is never started and the window is the whole graph,
update for update what ``PoseGraph`` does (same factor indices, same estimate), until a flush.
"""

from __future__ import annotations

import logging
import os
import queue
import socket
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass, replace
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import gtsam
import numpy as np

from graph.errors import SolverError
from graph.factors import FactorKind, FactorRecord, from_columns, pose_noise, position_covariance
from graph.keyframes import Keyframes
from graph.landmarks import Landmarks
from graph.pose_graph import NoiseSettings, PoseGraph

log = logging.getLogger(__name__)

MAX_CHILD_STARTS = 3  # a child that keeps failing is not restarted again


@dataclass(frozen=True)
class WindowSettings:
    """Keyframes in the iSAM2 window after a roll, and how many more it takes before the next roll."""

    window_keyframes: int = 400
    window_step: int = 100


class _Result:
    """The new factors' indices of one update (the part of ``ISAM2Result`` the callers read)."""

    def __init__(self, indices: list[int]):
        self._indices = indices

    def getNewFactorsIndices(self) -> list[int]:
        return self._indices


class WindowedGraph(Keyframes, Landmarks):
    """Keyframe poses and landmarks: a bounded iSAM2 window in front, the whole graph solved in a child."""

    def __init__(self, noise: NoiseSettings = NoiseSettings(), window: WindowSettings = WindowSettings()):
        if window.window_keyframes < 2 or window.window_step < 1:
            raise ValueError("the window needs at least 2 keyframes and a step of at least 1")
        self.noise, self.window = noise, window
        self.local = PoseGraph(noise)
        self.start = 0  # first keyframe in the window; the ones before are fixed
        self.factors: list[FactorRecord] = []  # every factor, global keyframe ids; index = factor index
        self._initial: list[np.ndarray] = []
        self._landmark_initial: list[np.ndarray] = []
        self._log: list[tuple] = []  # PoseGraph's update log, so the child (and a snapshot) can replay it
        self._landmarks: dict[int, int] = {}
        self._pending: dict[int, list[FactorRecord]] = {}
        self._removed: set[int] = set()
        self._to_local: dict[int, int] = {}  # factor index -> the window's factor index
        self._by_keyframe: dict[int, list[int]] = {}  # keyframe -> indices of the factors on it
        self._by_landmark: dict[int, list[int]] = {}  # landmark -> indices of the factors on it
        self._fixed = np.zeros((0, 4, 4))  # keyframes before ``start``
        self._frozen: dict[int, np.ndarray] = {}  # landmarks in the graph but not in the window
        self._global: _GlobalSolver | None = None
        self._child_starts = 0
        self.global_solves = 0  # global estimates applied to the window
        self.rebuilt = False  # until the window is first rebuilt it is the whole graph, update for update
        self.num_keyframes = self.num_factors = self.updates = 0

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

    # ------------------------------------------------------------ the update

    def _update(
        self,
        factors: list[FactorRecord],
        poses: list[np.ndarray] = (),
        landmarks: list[tuple[int, np.ndarray]] = (),
        remove: list[int] | None = None,
    ) -> _Result:
        """One update of the window (factors in global ids), recorded and passed on to the whole graph."""
        remove = list(remove or [])
        first, new = len(self.factors), {j for j, _ in landmarks}
        local, owners, revived = [], [], []
        local_landmarks = {j: p for j, p in landmarks}
        for j in self._touched(factors) - new - self.local.landmarks_in_solver():
            if j in self._frozen:  # back into the window, its measurements from fixed keyframes as priors
                for i in self._by_landmark.get(j, []):
                    if i not in self._removed and (r := self._localize(self.factors[i], {j})) is not None:
                        local.append(r)
                        owners.append(i)
                local_landmarks[j] = self._frozen[j]
                revived.append(j)
        keep = self.local.landmarks_in_solver() | new | set(revived)
        for i, f in enumerate(factors, start=first):
            r = self._localize(f, keep)
            if r is not None:
                local.append(r)
                owners.append(i)
        local_remove = [self._to_local[i] for i in remove if i in self._to_local]
        result = self.local._update(
            local, [np.asarray(p, float) for p in poses], list(local_landmarks.items()), local_remove
        )
        for i, li in zip(owners, result.getNewFactorsIndices()):
            self._to_local[i] = int(li)
        for i in remove:
            self._to_local.pop(i, None)
        for j in revived:
            del self._frozen[j]
        self._record(factors, poses, landmarks, remove)
        if self._global is not None and (factors or poses or remove):
            self._global.send(factors, [np.asarray(p, float) for p in poses], list(landmarks), remove, first)
        if self.num_keyframes - self.start >= self.window.window_keyframes + self.window.window_step:
            self._roll()
        return _Result(list(range(first, first + len(factors))))

    def _record(self, factors: list[FactorRecord], poses, landmarks, remove: list[int]) -> None:
        self._index(factors, len(self.factors))
        super()._record(factors, poses, landmarks, remove)
        for j in set(self._frozen) - set(self._landmarks):  # lost their last factor
            del self._frozen[j]

    def _drop_unconstrained(self, removed: list[int]) -> None:
        for j in self._touched([self.factors[i] for i in removed]) & self._landmarks.keys():
            if all(i in self._removed for i in self._by_landmark.get(j, [])):
                del self._landmarks[j]
                self._pending[j] = []
                log.info("landmark %d lost its last factor: out of the solver until observable again", j)

    def _touched(self, factors: list[FactorRecord]) -> set[int]:
        return {j for f in factors for _, j in _ends(f) if j is not None}

    def _localize(self, f: FactorRecord, landmarks: set[int]) -> FactorRecord | None:
        """A factor in the window's keyframe ids; one on a fixed keyframe as a prior on its other end; None when
        nothing of it is in the window (both keyframes fixed, or a landmark not in ``landmarks``)."""
        s, fixed = self.start, self._fixed
        if f.kind == FactorKind.LANDMARK:
            if f.b is None:
                return f if f.a in landmarks else None
            if f.b not in landmarks:
                return None
            if f.a >= s:
                return replace(f, a=f.a - s)
            T = fixed[f.a]
            R = T[:3, :3]
            covariance = (
                None
                if f.range_sigma_m is None
                else R @ position_covariance(f.measurement, f.sigma_m, f.range_sigma_m) @ R.T
            )
            return FactorRecord(
                f.b, None, R @ f.measurement + T[:3, 3], f.sigma_m, 0.0, f.huber_k, FactorKind.LANDMARK, covariance
            )
        if f.b is None:
            return replace(f, a=f.a - s) if f.a >= s else None
        if f.a >= s and f.b >= s:
            return replace(f, a=f.a - s, b=f.b - s)
        if f.b >= s:
            return replace(f, a=f.b - s, b=None, measurement=fixed[f.a] @ f.measurement)
        if f.a >= s:  # the prior's error is -Ad(T_ab) times the between-factor's: its covariance transformed so
            adjoint = gtsam.Pose3(f.measurement).AdjointMap()
            covariance = f.covariance if f.covariance is not None else pose_noise(f.sigma_m, f.sigma_deg).covariance()
            return replace(
                f,
                b=None,
                a=f.a - s,
                measurement=fixed[f.b] @ np.linalg.inv(f.measurement),
                covariance=adjoint @ covariance @ adjoint.T,
            )
        return None

    # ------------------------------------------------------------ rolling and re-anchoring

    def _roll(self) -> None:
        """Fix the oldest ``window_step`` keyframes and rebuild the window without them, at the whole graph's
        newest estimate when one has come back (else at the current one); then ask for the next solve."""
        child = self._child()
        solved = child.receive(0.0) if child is not None else None
        if self._rebuild(self.num_keyframes - self.window.window_keyframes, *self._anchored(solved)) and solved:
            self.global_solves += 1
        if child is not None:
            child.request()

    def _child(self) -> _GlobalSolver | None:
        """The whole-graph child, started (again, replaying everything) when it is not running; None once it
        failed ``MAX_CHILD_STARTS`` times: the window then goes on alone, its fixed past as it stands."""
        if self._global is not None and not self._global.dead:
            return self._global
        if self._global is not None:
            log.error("the whole-graph child process stopped (exit code %s)", self._global.exit_code())
            self._global.close()
            self._global = None
        if self._child_starts >= MAX_CHILD_STARTS:
            return None
        self._child_starts += 1
        try:
            self._global = _GlobalSolver(self)
        except OSError as exc:
            log.error("cannot start the whole-graph child process: %s", exc)
        return self._global

    def _anchored(
        self, solved: tuple[np.ndarray, dict[int, np.ndarray]] | None
    ) -> tuple[np.ndarray, dict[int, np.ndarray]]:
        """Every keyframe and landmark estimate, from a whole-graph solve where it has them: keyframes and
        landmarks that came later move rigidly with the newest solved keyframe."""
        current, landmarks = self.poses(), self.landmarks()
        n = 0 if solved is None else min(len(solved[0]), len(current))
        if n == 0:
            return current, landmarks
        poses, solved_landmarks = solved
        correction = poses[n - 1] @ np.linalg.inv(current[n - 1])
        moved = np.concatenate([poses[:n], correction @ current[n:]])
        merged = {j: correction[:3, :3] @ p + correction[:3, 3] for j, p in landmarks.items()}
        merged.update({j: p for j, p in solved_landmarks.items() if j in self._landmarks})
        return moved, merged

    def _rebuild(self, start: int, estimate: np.ndarray, landmarks: dict[int, np.ndarray]) -> bool:
        """A new window from ``start`` at the given estimate: one batch update of its keyframes and landmarks.
        False (and the window as it was) if iSAM2 rejects it."""
        old = self.start, self._fixed, self.local, self._to_local, self._frozen
        self.start, self._fixed = start, estimate[:start].copy()
        window = range(start, self.num_keyframes)
        indices = sorted({i for k in window for i in self._by_keyframe.get(k, []) if i not in self._removed})
        kept = {
            f.b
            for f in (self.factors[i] for i in indices)
            if f.kind == FactorKind.LANDMARK and f.b is not None and f.a >= start
        }
        kept &= self._landmarks.keys()
        indices = sorted(
            set(indices) | {i for j in kept for i in self._by_landmark.get(j, []) if i not in self._removed}
        )
        local, owners = [], []
        for i in indices:
            if (r := self._localize(self.factors[i], kept)) is not None:
                local.append(r)
                owners.append(i)
        graph = PoseGraph(self.noise)
        graph.timings, graph.factorization = self.timings, self.local.factorization
        graph.isam = graph._new_isam()
        try:
            result = graph._update(local, list(estimate[start:]), [(j, landmarks[j]) for j in sorted(kept)])
        except SolverError as exc:
            log.error("rebuilding the iSAM2 window failed, keeping the previous one: %s", exc)
            self.start, self._fixed, self.local, self._to_local, self._frozen = old
            return False
        self.local, self.rebuilt = graph, True
        self._to_local = {i: int(li) for i, li in zip(owners, result.getNewFactorsIndices())}
        self._frozen = {j: np.asarray(landmarks[j], float) for j in self._landmarks.keys() - kept}
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
        child = self._child()
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
        factors is which (before that the window is the whole graph, replayed from the log)."""
        window = {
            "settings": asdict(self.window),
            "start": self.start,
            "landmarks": np.array(sorted(self._landmarks), np.int64),
            "removed": np.array(sorted(self._removed), np.int64),
        }
        if self.rebuilt:
            frozen = sorted(self._frozen)
            window.update(
                {
                    "fixed": self._fixed.copy(),
                    "frozen": np.array(frozen, np.int64),
                    "frozen_estimates": np.array([self._frozen[j] for j in frozen]).reshape(-1, 3),
                    "local": self.local.state(),
                    "to_local": np.array(sorted(self._to_local.items()), np.int64).reshape(-1, 2),
                }
            )
        return {**PoseGraph.state(self), "window": window}  # the replay log's fields, kept here under the same names

    @classmethod
    def from_state(cls, state: dict[str, Any], window: WindowSettings | None = None) -> WindowedGraph:
        """The graph of ``state()`` (or of ``PoseGraph.state()``), its estimate exactly as saved: the window's
        iSAM2 replayed update for update (a window that never rolled is the whole graph), the fixed keyframes
        and frozen landmarks as they were, and the whole graph replayed in a new child."""
        saved = state.get("window")
        settings = window or (WindowSettings(**saved["settings"]) if saved else WindowSettings())
        rebuilt = bool(saved) and "local" in saved
        local = PoseGraph.from_state(saved["local"] if rebuilt else state)
        graph = cls(local.noise, settings)
        graph.local, graph.rebuilt = local, rebuilt
        if not rebuilt:  # the window is the whole graph: its books are the graph's
            graph.factors, graph._initial = list(local.factors), list(local._initial)
            graph._landmark_initial, graph._log = list(local._landmark_initial), list(local._log)
            graph._landmarks, graph._pending = dict(local._landmarks), local._pending
            local._pending = {}  # held-back observations are the graph's (the mixin of each keeps its own)
            graph._removed = set(local._removed)
            graph.num_keyframes, graph.num_factors, graph.updates = (
                local.num_keyframes,
                local.num_factors,
                local.updates,
            )
            graph._to_local = {i: i for i in range(len(local.factors)) if i not in local._removed}
            graph._index(graph.factors, 0)
            return graph
        graph.factors = from_columns(state["factors"])
        graph._initial, graph._landmark_initial = list(state["initial"]), list(state["landmark_initial"])
        graph._log = [tuple(e) for e in state["updates"]]
        graph._landmarks = {int(j): i for i, j in enumerate(saved["landmarks"])}
        pending = from_columns(state["pending"])
        graph._pending = {int(j): [r for r in pending if r.b == j] for j in state["pending_landmarks"]}
        graph._removed = {int(i) for i in saved["removed"]}
        graph.num_keyframes = sum(e[1] for e in graph._log)
        graph.num_factors = len(graph.factors) - len(graph._removed)
        graph.updates = len(graph._log)
        graph._index(graph.factors, 0)
        graph.start, graph._fixed = int(saved["start"]), np.asarray(saved["fixed"], float)
        graph._frozen = {int(j): np.asarray(p, float) for j, p in zip(saved["frozen"], saved["frozen_estimates"])}
        graph._to_local = {int(i): int(li) for i, li in saved["to_local"]}
        if graph.start:
            graph._child()
        return graph

    def _index(self, factors: list[FactorRecord], first: int) -> None:
        """Index factors (numbered from ``first``) by the keyframes and landmarks they constrain."""
        for i, f in enumerate(factors, start=first):
            for k, j in _ends(f):
                if k is not None:
                    self._by_keyframe.setdefault(k, []).append(i)
                if j is not None:
                    self._by_landmark.setdefault(j, []).append(i)


def _ends(f: FactorRecord) -> list[tuple[int | None, int | None]]:
    """(keyframe, landmark) of each variable a factor constrains (one of the two is None)."""
    if f.kind == FactorKind.LANDMARK:
        return [(None, f.a)] if f.b is None else [(f.a, None), (None, f.b)]
    return [(f.a, None)] if f.b is None else [(f.a, None), (f.b, None)]


class _GlobalSolver:
    """The whole graph in a child process: fed every update, solves when asked, sends its estimate back.

    A plain ``python -m graph.window`` child over a socket pair rather than ``multiprocessing``'s spawn, which
    would re-import the parent's main script (and run it, in any script without a ``__main__`` guard). A reader
    thread takes the estimates as they come, so neither side ever blocks on a full socket while the other does.
    """

    def __init__(self, graph: WindowedGraph):
        ours, theirs = socket.socketpair()
        root = str(Path(__file__).resolve().parent.parent)
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)}
        self._process = subprocess.Popen(
            [sys.executable, "-m", "graph.window", str(theirs.fileno())], pass_fds=[theirs.fileno()], env=env
        )
        theirs.close()
        self._conn = Connection(ours.detach())
        self._asked = self._answered = 0
        self._newest: tuple[np.ndarray, dict[int, np.ndarray]] | None = None
        self._asked_at: dict[int, float] = {}
        self.dead = False  # set when the child's socket closes (it exited or crashed)
        self.latencies: list[float] = []  # seconds from each request to its estimate's arrival
        self._arrived = threading.Condition()
        self._outbox: queue.SimpleQueue = queue.SimpleQueue()
        threading.Thread(target=self._read, name="objslam-global-graph-in", daemon=True).start()
        threading.Thread(target=self._write, name="objslam-global-graph-out", daemon=True).start()
        # the history so far, replayed by the child before anything else
        self._outbox.put(
            (
                "replay",
                graph.noise,
                list(graph.factors),
                list(graph._initial),
                list(graph._landmark_initial),
                list(graph._log),
            )
        )

    def _write(self) -> None:
        """Messages go out from this thread: the window never waits for the child to read."""
        while True:
            message = self._outbox.get()
            try:
                self._conn.send(message)
            except OSError:
                with self._arrived:
                    self.dead = True
                    self._arrived.notify_all()
                return
            if message is None:
                return

    def _read(self) -> None:
        while True:
            try:
                token, poses, landmarks = self._conn.recv()
            except (EOFError, OSError):  # the child is gone: nobody waits for it any longer
                with self._arrived:
                    self.dead = True
                    self._arrived.notify_all()
                return
            with self._arrived:
                self._answered, self._newest = token, (poses, landmarks)
                self.latencies.append(time.perf_counter() - self._asked_at[token])
                self._asked_at = {t: at for t, at in self._asked_at.items() if t > token}
                self._arrived.notify_all()

    @property
    def outstanding(self) -> bool:
        """Whether a requested solve has not come back."""
        with self._arrived:
            return self._answered < self._asked

    def exit_code(self) -> int | None:
        return self._process.poll()

    def send(self, factors, poses, landmarks, remove, first: int) -> None:
        if not self.dead:  # a dead child is replaced by a new one that replays everything
            self._outbox.put(("update", factors, poses, landmarks, remove, first))

    def request(self, exact: bool = False) -> None:
        """Ask for a solve of everything sent so far: iSAM2's estimate, not while one is still outstanding; or
        ``exact``, the batch optimum (``PoseGraph.optimum``), in any case."""
        with self._arrived:
            if self.dead or (self._answered < self._asked and not exact):
                return
            self._asked += 1
            asked = self._asked
            self._asked_at[asked] = time.perf_counter()
        self._outbox.put(("solve", asked, exact))

    def receive(self, wait: float) -> tuple[np.ndarray, dict[int, np.ndarray]] | None:
        """The newest estimate not taken yet (waiting up to ``wait`` s for the last request's), or None."""
        with self._arrived:
            self._arrived.wait_for(lambda: self._answered >= self._asked or self.dead, timeout=wait)
            newest, self._newest = self._newest, None
        return newest

    def close(self) -> None:
        self._outbox.put(None)
        try:
            self._process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._process.kill()
        self._conn.close()


def _serve(conn: Connection) -> None:
    """The child: a full ``PoseGraph`` fed in order. The updates that queued up while it solved go in as one
    iSAM2 update (split where one removes factors); then one solve if any message asked for it."""
    graph = PoseGraph()
    index: dict[int, int] = {}  # the parent's factor index -> this graph's
    while True:
        try:
            messages = [conn.recv()]
            while conn.poll():
                messages.append(conn.recv())
        except EOFError:  # the parent is gone
            return
        if None in messages:
            return
        asked, exact, batch = 0, False, []
        for kind, *body in messages:
            if kind == "replay":
                noise, factors, initial, landmark_initial, entries = body
                graph = PoseGraph(noise)
                graph._replay(entries, factors, initial, landmark_initial)
                index = {i: i for i in range(len(factors))}
            elif kind == "update":
                if body[3]:  # removals refer to factors already in: apply what queued before them first
                    _apply(graph, batch, index)
                    batch = []
                batch.append(body)
            else:
                asked, exact = body[0], exact or body[1]
        _apply(graph, batch, index)
        if asked:
            graph._converge(10)
            conn.send((asked, *(graph.optimum() if exact else (graph.poses(), graph.landmarks()))))


def _apply(graph: PoseGraph, batch: list[tuple], index: dict[int, int]) -> None:
    """Updates of the parent as one update of the whole graph (one by one if iSAM2 rejects them together)."""
    if not batch:
        return
    factors = [f for b in batch for f in b[0]]
    poses = [p for b in batch for p in b[1]]
    landmarks = [lm for b in batch for lm in b[2]]
    remove = [index[i] for b in batch for i in b[3] if i in index]
    try:
        result = graph._update(factors, poses, landmarks, remove)
    except SolverError as exc:
        if len(batch) == 1:  # out of step with the parent from here on: exit, to be restarted with a replay
            raise SystemExit(f"the whole graph rejected an update the window took: {exc}") from exc
        for one in batch:
            _apply(graph, [one], index)
        return
    new = iter(int(i) for i in result.getNewFactorsIndices())
    for fs, _, _, _, first in batch:
        index.update((first + i, next(new)) for i in range(len(fs)))


if __name__ == "__main__":
    _serve(Connection(int(sys.argv[1])))
