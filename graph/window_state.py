"""A windowed graph's plain state in two parts (``window_parts``): what the window bounds, and the append-only
logs. A map store writes the logs row by row as they grow and the rest whole, so what it writes per keyframe
does not grow with the map; ``joined`` gives the ``state()`` format that ``WindowedGraph.from_state`` reads.

The logs: the whole graph's factor records, guesses and update log; once the window was rebuilt, the fixed
past (replaced at each roll), and the window's own iSAM2 books and which global factor each of its factors
stands for (both replaced at each rebuild, then growing with the window). Removed factors are not saved: the
update log says which they are.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from graph.books import Books, joined_columns
from graph.factors import from_columns
from graph.settings import noise_state, window_state
from graph.window_factors import fused_owners

if TYPE_CHECKING:
    from graph.window import WindowedGraph

LOGS = ("factors", "initial", "landmark_initial", "updates")


def window_parts(g: WindowedGraph) -> tuple[dict[str, Any], dict[str, Any]]:
    """``g.state()`` in two parts, without the estimates (a replay's check, which ``state()`` adds)."""
    books_small, logs = g.books.parts()
    window: dict[str, Any] = {
        "settings": window_state(g.settings),
        "start": g.start,
        "landmarks": np.array(sorted(g.books.landmarks), np.int64),
    }
    small: dict[str, Any] = {
        "noise": noise_state(g.settings),
        "factorization": g.factorization,
        **books_small,
        "window": window,
    }
    if g.rebuilt:
        frozen = sorted(g._frozen)
        local_small, local_logs = g.local.books.parts()
        window.update(
            {
                "frozen": np.array(frozen, np.int64),
                "frozen_estimates": np.array([g._frozen[j] for j in frozen]).reshape(-1, 3),
                "local": {
                    "noise": noise_state(g.local.settings),
                    "factorization": g.local.factorization,
                    **local_small,
                },
            }
        )
        logs.update({f"local.{name}": rows for name, rows in local_logs.items()})
        logs["local_pairs"], logs["fixed"] = g._local_pairs, g._fixed
    else:  # the window is the whole graph and bounded by it: its estimate checks the replay
        small["estimate"] = g.poses()
    return small, logs


def joined(small: dict[str, Any], logs: dict[str, Any], records: bool = False) -> dict[str, Any]:
    """``WindowedGraph.state()`` of its parts (logs as lists or arrays, of any sequence type), without the
    estimates of a rebuilt window; ``records``: the factors as records, not columns (``joined_columns``)."""
    state = {k: v for k, v in small.items() if k != "window"}
    state.update(joined_columns({}, {name: logs[name] for name in LOGS}, records))
    window = dict(small["window"])
    removed = sorted({int(i) for entry in state["updates"] for i in entry[2]})  # what ``Books.record`` removed
    window["removed"] = np.array(removed, np.int64)
    if "fixed" in logs:
        window["fixed"] = np.array(logs["fixed"], float).reshape(-1, 4, 4)
        local = joined_columns({}, {name: logs[f"local.{name}"] for name in LOGS}, records)
        window["local"] = {**window["local"], **local}
        gone = set(removed)
        pairs = sorted((i, li) for i, li in dict(logs["local_pairs"]).items() if i not in gone)
        window["to_local"] = np.array(pairs, np.int64).reshape(-1, 2)
    state["window"] = window
    return state


def restore_rolled(graph: WindowedGraph, state: dict[str, Any], saved: dict[str, Any]) -> None:
    """The books, fixed past, frozen landmarks and factor map of a rolled window (``state()``, its ``window``
    part ``saved``) into ``graph``, whose window's own iSAM2 is already replayed."""
    log_entries = [tuple(e) for e in state["updates"]]
    factors = from_columns(state["factors"])
    removed = {int(i) for i in saved["removed"]}
    pending = from_columns(state["pending"])
    graph.books = Books(
        factors=factors,
        initial=list(state["initial"]),
        landmark_initial=list(state["landmark_initial"]),
        log=log_entries,
        landmarks={int(j): i for i, j in enumerate(saved["landmarks"])},
        pending={int(j): [r for r in pending if r.b == j] for j in state["pending_landmarks"]},
        removed=removed,
        num_keyframes=sum(e[1] for e in log_entries),
        num_factors=len(factors) - len(removed),
        updates=len(log_entries),
    )
    graph._index.add(graph.factors, 0)
    graph.start, graph._fixed = int(saved["start"]), np.asarray(saved["fixed"], float)
    graph._frozen = {
        int(j): np.asarray(p, float) for j, p in zip(saved["frozen"], saved["frozen_estimates"], strict=True)
    }
    graph._to_local = {int(i): int(li) for i, li in saved["to_local"]}
    graph._local_pairs = list(graph._to_local.items())
    graph._fused = fused_owners(graph._to_local)
