"""A windowed graph's plain state from its two parts (``WindowedGraph.parts``): the part the window bounds and
the append-only logs of the whole graph. A map store writes the logs row by row as they grow and the rest
whole; ``joined`` gives the ``state()`` format that ``WindowedGraph.from_state`` reads back."""

from __future__ import annotations

from typing import Any

import numpy as np

from graph.factors import to_columns


def joined(small: dict[str, Any], logs: dict[str, Any]) -> dict[str, Any]:
    """``WindowedGraph.state()`` of its parts (logs as lists or arrays, of any sequence type)."""
    state = {
        **{k: v for k, v in small.items() if k != "window"},
        "factors": to_columns(list(logs["factors"])),
        "initial": np.array(list(logs["initial"]), float).reshape(-1, 4, 4),
        "landmark_initial": np.array(list(logs["landmark_initial"]), float).reshape(-1, 3),
        "updates": list(logs["updates"]),
        "window": dict(small["window"]),
    }
    removed = sorted({int(i) for entry in state["updates"] for i in entry[2]})  # what ``Books.record`` removed
    state["window"]["removed"] = np.array(removed, np.int64)
    if "fixed" in logs:
        state["window"]["fixed"] = np.array(logs["fixed"], float).reshape(-1, 4, 4)
    if "estimate" not in state:  # rebuilt: the window's own state checks its replay; the fixed past is as saved
        state["estimate"] = np.concatenate([state["window"]["fixed"], state["window"]["local"]["estimate"]])
    return state
