"""``save`` queries: queued by the zenoh callback, answered by the worker between two frames."""

from __future__ import annotations

import json
import logging
import queue
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh

log = logging.getLogger(__name__)


class SaveRequests:
    """A bounded queue of ``save`` queries and the worker's answers (the outputs written into the state dir)."""

    def __init__(
        self, robot: str, prefix: str, state_dir: Path | None, write: Callable[[Path], dict[str, Any]], size: int = 4
    ):
        self.robot, self.prefix, self.state_dir, self.write = robot, prefix, state_dir, write
        self._queries: queue.Queue[zenoh.Query] = queue.Queue(maxsize=size)

    def enqueue(self, query: zenoh.Query) -> None:
        """The queryable's callback: only queues the query (or refuses it when too many wait)."""
        try:
            self._queries.put_nowait(query)
        except queue.Full:
            query.reply_err(json.dumps({"error": "busy: earlier save requests are still being written"}).encode())

    def answer(self) -> None:
        """Write the outputs for every waiting query and reply (worker thread, between frames)."""
        while True:
            try:
                query = self._queries.get_nowait()
            except queue.Empty:
                return
            try:
                query.reply(
                    f"{self.prefix}/save", json.dumps(self._save()).encode(), encoding=zenoh.Encoding.APPLICATION_JSON
                )
            except Exception as exc:  # a failed save must not take the service down
                log.exception("save request failed")
                query.reply_err(json.dumps({"error": str(exc)}).encode())
            finally:
                del query  # dropping it finalizes the query for the client

    def _save(self) -> dict[str, Any]:
        if self.state_dir is None:
            raise ValueError("this service has no state directory (serve --state-dir DIR) to write to")
        t0 = time.perf_counter()
        out = Path(self.state_dir)
        summary = self.write(out)
        return {
            "robot": self.robot,
            "dir": str(out),
            "files": sorted(path.name for path in out.iterdir() if path.is_file()),
            "keyframes": summary["keyframes"],
            "frames_processed": summary["frames_processed"],
            "seconds": round(time.perf_counter() - t0, 3),
        }

    def refuse_all(self, reason: str) -> None:
        """Reply an error to every waiting query (the service is stopping)."""
        while True:
            try:
                query = self._queries.get_nowait()
            except queue.Empty:
                return
            query.reply_err(json.dumps({"error": reason}).encode())
