"""``objslam run``: the whole service on an embedded zenoh session, replaying as fast as it processes."""

from __future__ import annotations

import threading
import time
from collections import deque

import pytest

import service.run
from service.config import load_settings
from service.run import run_dataset
from sources import open_dataset
from sources.base import Dataset

pytestmark = pytest.mark.integration
FRAMES = 300


class Rendered(Dataset):
    """Frames rendered once beforehand, so the replay publishes faster than the service processes."""

    def __init__(self, spec: str):
        source = open_dataset(spec)
        self.name, self.camera = source.name, source.camera
        self._frames = [source.frame(i) for i in range(len(source))]

    def __len__(self) -> int:
        return len(self._frames)

    def frame(self, index: int):
        return self._frames[index]


@pytest.fixture(scope="module")
def rendered() -> Rendered:
    return Rendered(f"synthetic:room?seed=0&frames={FRAMES}&width=320&height=240")


class LateDelivery:
    """A publisher whose messages reach zenoh ``delay_s`` late: frames in flight that no queue shows yet."""

    def __init__(self, pub, delay_s: float):
        self._pub, self._delay = pub, delay_s
        self._pending: deque[tuple[float, bytes]] = deque()
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._forward, daemon=True)
        self._thread.start()

    def put(self, payload: bytes) -> None:
        self._pending.append((time.monotonic() + self._delay, payload))

    def _forward(self) -> None:
        while not (self._closed.is_set() and not self._pending):
            if self._pending and self._pending[0][0] <= time.monotonic():
                self._pub.put(self._pending.popleft()[1])
            else:
                time.sleep(0.001)

    def undeclare(self) -> None:
        self._closed.set()
        self._thread.join()
        self._pub.undeclare()


@pytest.mark.parametrize("delay_s", [0.0, 0.1])
def test_run_on_300_frames_drops_none_even_when_zenoh_delivers_late(tmp_path, monkeypatch, rendered, delay_s):
    publisher = service.run.frame_publisher
    monkeypatch.setattr(service.run, "frame_publisher", lambda *a, **kw: LateDelivery(publisher(*a, **kw), delay_s))
    summary = run_dataset(rendered, tmp_path, load_settings(None, {"ingest": {"queue_size": 8}}), progress=False)
    assert summary["frames_dropped"] == 0
    assert summary["frames_processed"] == FRAMES and summary["frames_rejected"] == {}
    assert "| frames_dropped | 0 |" in (tmp_path / "report.md").read_text()
