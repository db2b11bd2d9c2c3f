"""Shared fixtures: small frames, the shared real dataset location, free ports."""

from __future__ import annotations

import socket
from pathlib import Path

import numpy as np
import pytest

from graph.geometry import pose_from_tum
from perception.frame import CameraModel, Detection, Frame, Intrinsics
from service.cli import single_threaded_blas

single_threaded_blas()  # as the objslam command does: tests run the pipeline as the service runs it

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
REDKITCHEN = SHARED_DATA / "7scenes_redkitchen_1000"


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


requires_redkitchen = pytest.mark.skipif(
    not REDKITCHEN.is_dir(), reason=f"real data not found at {REDKITCHEN} (../shared/data is absent)"
)
