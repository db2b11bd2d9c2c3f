"""The service's heap and Python's cyclic garbage collector.

A map is millions of small long-lived objects (frame records, factors, feature vectors). The collector's full
collections scan all of them, so on a map of thousands of keyframes each one stalls the worker for 60-300 ms,
and a restore, which makes them all at once, triggers one after another (a restart grew faster than the map).
What the map holds never becomes cyclic garbage: it is moved out of the collector's reach (``gc.freeze``), and
the collector waits while a restore builds it. Cyclic garbage made before a freeze and freed after is never
collected: ``objslam bench longrun``'s RSS per keyframe measures that this stays small.
"""

from __future__ import annotations

import gc
from collections.abc import Iterator
from contextlib import contextmanager


def settle_map() -> None:
    """What is alive now is mostly the map, and the map lives on: full collections leave it alone from now."""
    gc.freeze()


@contextmanager
def building_map() -> Iterator[None]:
    """No collections while a map is restored (nothing it makes is garbage); its objects settled after."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        settle_map()
        if enabled:
            gc.enable()
