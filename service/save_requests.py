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

from service.budget import TokenBucket
from service.config import Settings

log = logging.getLogger(__name__)


class SaveRequests:
    """A bounded queue of ``save`` queries and the worker's answers (the outputs written into the state dir)."""

    def __init__(self, settings: Settings, service_id: str, write: Callable[[Path], dict[str, Any]]):
        robot, prefix, state_dir = settings.robot, settings.key_prefix, settings.state_dir
        min_interval_s = settings.ingest.min_save_interval_s
        self.robot, self.prefix, self.state_dir, self.write = robot, prefix, state_dir, write
        self.service_id = service_id
        self._queries: queue.Queue[zenoh.Query] = queue.Queue(maxsize=1)
        # one save per interval: each one stops the worker while it writes (a flood of saves dropped frames)
        self.budget = TokenBucket(1.0 / min_interval_s, 1.0) if min_interval_s > 0 else None
        self.busy = 0

    def enqueue(self, query: zenoh.Query) -> None:
        """The queryable's callback: only queues the query, or answers 'busy' when one is waiting or being
        written, or the last one was less than ``min_interval_s`` ago."""
        if self.budget is not None and not self.budget.take():
            self._refuse_busy(query, "the last save was too recent (ingest.min_save_interval_s)")
            return
        try:
            self._queries.put_nowait(query)
        except queue.Full:
            self._refuse_busy(query, "a save is already waiting to be written")

    def _refuse_busy(self, query: zenoh.Query, why: str) -> None:
        self.busy += 1
        query.reply_err(json.dumps({"error": f"busy: {why}", "service_id": self.service_id}).encode())

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
            "service_id": self.service_id,
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
