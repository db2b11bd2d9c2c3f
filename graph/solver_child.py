"""The whole-graph child process: ``python -m graph.solver_child FD`` (started by ``graph.solver_proxy``).

A full ``PoseGraph`` fed, in order, every update of the window over the socket ``FD`` (``graph.solver_messages``);
it solves when asked and sends the estimate back. Nothing is shared with the parent.
"""

from __future__ import annotations

import sys
from multiprocessing.connection import Connection

from graph.errors import SolverError
from graph.pose_graph import PoseGraph
from graph.solver_messages import Replay, Solution, Solve, Stop, ToChild, Update


def serve(conn: Connection) -> None:
    """The child's loop: the updates that queued up while it solved go in as one iSAM2 update (split where one
    removes factors); then one solve if any message asked for it."""
    graph = PoseGraph()
    index: dict[int, int] = {}  # the parent's factor index -> this graph's
    while True:
        try:
            messages: list[ToChild] = [conn.recv()]
            while conn.poll():
                messages.append(conn.recv())
        except EOFError:  # the parent is gone
            return
        if any(isinstance(m, Stop) for m in messages):
            return
        asked, exact = 0, False
        batch: list[Update] = []
        for message in messages:
            if isinstance(message, Replay):
                graph = PoseGraph(message.settings)
                graph.replay(message.log, message.factors, message.initial, message.landmark_initial)
                index = {i: i for i in range(len(message.factors))}
            elif isinstance(message, Update):
                if message.remove:  # removals refer to factors already in: apply what queued before them first
                    _apply(graph, batch, index)
                    batch = []
                batch.append(message)
            elif isinstance(message, Solve):
                asked, exact = message.token, exact or message.exact
        _apply(graph, batch, index)
        if asked:
            graph.converge(10)
            poses, landmarks = graph.optimum() if exact else (graph.poses(), graph.landmarks())
            conn.send(Solution(asked, poses, landmarks))


def _apply(graph: PoseGraph, batch: list[Update], index: dict[int, int]) -> None:
    """Updates of the parent as one update of the whole graph (one by one if iSAM2 rejects them together)."""
    if not batch:
        return
    factors = [f for b in batch for f in b.factors]
    poses = [p for b in batch for p in b.poses]
    landmarks = [lm for b in batch for lm in b.landmarks]
    remove = [index[i] for b in batch for i in b.remove if i in index]
    try:
        result = graph.update(factors, poses, landmarks, remove)
    except SolverError as exc:
        if len(batch) == 1:  # out of step with the parent from here on: exit, to be restarted with a replay
            raise SystemExit(f"the whole graph rejected an update the window took: {exc}") from exc
        for one in batch:
            _apply(graph, [one], index)
        return
    new = iter(result.factor_indices)
    for b in batch:
        index.update((b.first + i, next(new)) for i in range(len(b.factors)))


if __name__ == "__main__":
    serve(Connection(int(sys.argv[1])))
