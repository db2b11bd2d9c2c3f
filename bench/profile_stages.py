"""The top costs of a py-spy profile (``py-spy record -f raw``): objslam's own functions by inclusive time.

A raw profile has one line per distinct stack, ``frame;frame;...;frame count`` (outermost first), each frame
``function (path:line)``. A function's inclusive samples are those of the stacks it appears in (once per stack,
however deep the recursion); only functions under the project's own packages are listed, by thread.
"""

from __future__ import annotations

import re
from collections import Counter
from pathlib import Path

PACKAGES = ("service/", "slam/", "perception/", "graph/", "loops/", "rl/", "sources/", "evaluation/")
FRAME = re.compile(r"^(?P<name>[^ ]+) \((?P<path>[^:]+):\d+\)$")
THREAD = re.compile(r"^(?:thread|process) \((?P<what>[^)]*)\)")


def _own(frame: str) -> str | None:
    """``function (package/module.py)`` for a frame of the project's code, else None."""
    m = FRAME.match(frame.strip())
    if m is None:
        return None
    path = m["path"]
    for package in PACKAGES:
        at = path.rfind(package)
        if at >= 0 and "site-packages" not in path:
            return f"{m['name']} ({path[at:]})"
    return None


def inclusive(raw: str) -> tuple[Counter[str], int]:
    """Inclusive samples per project function, and all samples."""
    counts: Counter[str] = Counter()
    total = 0
    for line in raw.splitlines():
        stack, _, n = line.rpartition(" ")
        if not stack or not n.isdigit():
            continue
        total += int(n)
        seen = {f for f in (_own(frame) for frame in stack.split(";")) if f is not None}
        for function in seen:
            counts[function] += int(n)
    return counts, total


def top_costs(path: Path, rate_hz: float, frames: int, top: int = 14) -> list[tuple[str, float, float]]:
    """(function, ms per frame, share of all samples) of the ``top`` costliest project functions."""
    counts, total = inclusive(path.read_text())
    return [(f, n / rate_hz / frames * 1e3, n / max(total, 1)) for f, n in counts.most_common(top)]
