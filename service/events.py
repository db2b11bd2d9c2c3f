"""``<prefix>/<robot>/events``: what changed in the map, published after each frame that changed it."""

from __future__ import annotations

import json
import logging
from typing import Any

import zenoh

from service.map_summary import MapSummary, loop_events

log = logging.getLogger(__name__)


class MapEvents:
    """The object map after each re-clustering, the loop closures accepted since the last event, and those
    retracted since (accepted earlier, removed when later loops contradicted them)."""

    def __init__(self) -> None:
        self.publisher: zenoh.Publisher | None = None
        self._version = 0
        self._accepted: set[int] = set()  # factor indices of the accepted loops last published
        self._loops_key: tuple[int, int] = (0, 0)

    def resume(self, object_map_version: int, accepted: set[int]) -> None:
        """Continue after a restored map: its objects and accepted loops are not news."""
        self._version, self._accepted = object_map_version, accepted

    def changes(self, summary: MapSummary) -> list[dict[str, Any]]:
        """The events of ``summary`` since the last call."""
        events = []
        if summary.object_map_version != self._version:
            events.append({"type": "objects", "objects": summary.objects})
            self._version = summary.object_map_version
        if summary.loops_key != self._loops_key:
            new_events, self._accepted = loop_events(summary.loops, self._accepted)
            events += new_events
            self._loops_key = summary.loops_key
        return events

    def publish(self, summary: MapSummary) -> None:
        for event in self.changes(summary):
            if self.publisher is None:
                continue
            try:
                self.publisher.put(json.dumps(event).encode())
            except zenoh.ZError as exc:
                log.warning("could not publish event: %s", exc)
