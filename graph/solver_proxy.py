"""The parent's side of the whole-graph child process (``graph.solver_child``): ``GlobalSolver``."""

from __future__ import annotations

import os
import queue
import socket
import subprocess
import sys
import threading
import time
from multiprocessing.connection import Connection
from pathlib import Path

from graph.solver_messages import Replay, Solution, Solve, Stop, ToChild, Update
from graph.window_factors import Estimate

CHILD_MODULE = "graph.solver_child"


class GlobalSolver:
    """The whole graph in a child process: fed every update, solves when asked, sends its estimate back.

    A plain ``python -m graph.solver_child`` child over a socket pair rather than ``multiprocessing``'s spawn,
    which would re-import the parent's main script (and run it, in any script without a ``__main__`` guard). A
    reader thread takes the estimates as they come, so neither side ever blocks on a full socket while the other
    does. ``history``: everything so far, replayed by the child before anything else.
    """

    def __init__(self, history: Replay):
        ours, theirs = socket.socketpair()
        root = str(Path(__file__).resolve().parent.parent)
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)}
        self._process = subprocess.Popen(
            [sys.executable, "-m", CHILD_MODULE, str(theirs.fileno())], pass_fds=[theirs.fileno()], env=env
        )
        theirs.close()
        self._conn = Connection(ours.detach())
        self._asked = self._answered = 0
        self._newest: Estimate | None = None
        self._asked_at: dict[int, float] = {}
        self.dead = False  # set when the child's socket closes (it exited or crashed)
        self.latencies: list[float] = []  # seconds from each request to its estimate's arrival
        self._arrived = threading.Condition()
        self._outbox: queue.SimpleQueue[ToChild] = queue.SimpleQueue()
        threading.Thread(target=self._read, name="objslam-global-graph-in", daemon=True).start()
        threading.Thread(target=self._write, name="objslam-global-graph-out", daemon=True).start()
        self._outbox.put(history)

    @property
    def pid(self) -> int:
        """The child's process id."""
        return self._process.pid

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
            if isinstance(message, Stop):
                return

    def _read(self) -> None:
        while True:
            try:
                solution: Solution = self._conn.recv()
            except (EOFError, OSError):  # the child is gone: nobody waits for it any longer
                with self._arrived:
                    self.dead = True
                    self._arrived.notify_all()
                return
            token = solution.token
            with self._arrived:
                self._answered, self._newest = token, (solution.poses, solution.landmarks)
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

    def send(self, update: Update) -> None:
        if not self.dead:  # a dead child is replaced by a new one that replays everything
            self._outbox.put(update)

    def request(self, exact: bool = False) -> None:
        """Ask for a solve of everything sent so far: iSAM2's estimate, not while one is still outstanding; or
        ``exact``, the batch optimum (``PoseGraph.optimum``), in any case."""
        with self._arrived:
            if self.dead or (self._answered < self._asked and not exact):
                return
            self._asked += 1
            asked = self._asked
            self._asked_at[asked] = time.perf_counter()
        self._outbox.put(Solve(asked, exact))

    def wait_idle(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s until no requested solve is outstanding, leaving its estimate to be taken by
        ``receive``; whether none is."""
        with self._arrived:
            return self._arrived.wait_for(lambda: self._answered >= self._asked or self.dead, timeout=timeout)

    def receive(self, wait: float) -> Estimate | None:
        """The newest estimate not taken yet (waiting up to ``wait`` s for the last request's), or None."""
        with self._arrived:
            self._arrived.wait_for(lambda: self._answered >= self._asked or self.dead, timeout=wait)
            newest, self._newest = self._newest, None
        return newest

    def close(self) -> None:
        self._outbox.put(Stop())
        try:
            self._process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._process.kill()
        self._conn.close()
