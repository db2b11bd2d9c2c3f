"""Shared fixtures: small frames, the shared real dataset location, free ports."""

from __future__ import annotations

import functools
import os
import socket
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from graph.geometry import pose_from_tum
from perception.frame import CameraModel, Detection, Frame, Intrinsics
from service.cli import single_threaded_blas

single_threaded_blas()  # as the objslam command does: tests run the pipeline as the service runs it

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
REDKITCHEN = SHARED_DATA / "7scenes_redkitchen_1000"
ROOM_POLICY = Path(__file__).resolve().parents[1] / "models" / "lc" / "room_seed3.onnx"


def make_frame(t: float = 1.0, seq: int = 0, width: int = 64, height: int = 48, seed: int = 0) -> Frame:
    """A small valid frame with odometry and one detection."""
    rng = np.random.default_rng(seed)
    camera = CameraModel(Intrinsics(50.0, 50.0, width / 2, height / 2), width, height, 1000.0)
    yy, xx = np.mgrid[0:height, 0:width]
    rgb = np.stack([xx * 255 // width, yy * 255 // height, (xx + yy) % 64 * 4], axis=-1).astype(np.uint8)
    depth = rng.integers(500, 4000, (height, width)).astype(np.uint16)
    odom = pose_from_tum(np.array([0.1 * t, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]))
    dets = [Detection("cup", 0.9, (5.0, 6.0, 20.0, 30.0))]
    return Frame(t, seq, f"test/{seq}", camera, rgb, depth, odom, dets)


@pytest.fixture
def frame() -> Frame:
    return make_frame()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def router():
    """A zenoh router on 127.0.0.1 (no multicast): (its session, the endpoint clients connect to)."""
    from bench.rig import router as open_router

    port = free_port()
    session = open_router(port)
    yield session, f"tcp/127.0.0.1:{port}"
    session.close()


def in_ci() -> bool:
    """A CI run: the environment sets ``CI`` (as ``.ci/run`` and the usual CI services do) to anything but
    empty, 0, false or no."""
    return os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")


def requires_data(path: Path, what: str) -> Callable[[Callable], Callable]:
    """Decorate a test that needs ``path``. Outside CI it is skipped when the path is absent; in CI it always
    runs and fails, naming what is missing, so that a CI run cannot pass by skipping the real-data tests."""

    def mark(test: Callable) -> Callable:
        if not in_ci():
            return pytest.mark.skipif(not path.exists(), reason=f"{what} not found at {path}")(test)

        @functools.wraps(test)  # keeps the test's signature, so its fixtures still reach it
        def checked(*args, **kwargs):
            if not path.exists():
                pytest.fail(f"{what} not found at {path}: a CI run (CI is set) must provide it", pytrace=False)
            return test(*args, **kwargs)

        return checked

    return mark


requires_redkitchen = requires_data(REDKITCHEN, "real data (7-Scenes redkitchen; ../shared/data beside the repo)")
requires_room_policy = requires_data(ROOM_POLICY, "the shipped room_seed3 policy")
