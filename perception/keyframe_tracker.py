"""Tracking between keyframes without features: the keyframe's 3D points followed by pyramidal Lucas-Kanade.

At a keyframe the front end extracts ORB and matches it (``perception.odometry``); that costs most of a frame's
tracking time and is only needed where a factor is made. Between keyframes this tracker takes up to
``max_points`` of the keyframe's keypoints that have depth (spread over a grid, so no wall of texture takes them
all), follows them from the keyframe's image into each new frame with pyramidal LK, each starting from where
a constant-velocity motion prior puts it (so the search stays small as the camera moves away), and checks every track
back from the frame to the keyframe (forward-backward error). The surviving 2D-3D correspondences go to the
same PnP-RANSAC + LM and the same acceptance as the feature matches. No state but the keyframe's: a frame the
tracker fails on goes to the feature path, which decides everything as before.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

WINDOW = (21, 21)
LEVELS = 3
CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.03)


@dataclass(frozen=True)
class Tracks:
    """Correspondences of one frame: the keyframe's colour-camera 3D points (N, 3) and their pixels (N, 2)."""

    points: np.ndarray
    pixels: np.ndarray

    def __len__(self) -> int:
        return len(self.points)


def spread(pixels: np.ndarray, shape: tuple[int, int], count: int, cell_px: int = 40) -> np.ndarray:
    """Indices of at most ``count`` of ``pixels`` taken round-robin over a grid of ``cell_px`` cells (their
    given order within a cell kept), so the points cover the image instead of its most textured part."""
    if len(pixels) <= count:
        return np.arange(len(pixels))
    cols = max(1, shape[1] // cell_px + 1)
    cell = (pixels[:, 1] // cell_px).astype(np.int64) * cols + (pixels[:, 0] // cell_px).astype(np.int64)
    order = np.argsort(cell, kind="stable")
    sorted_cells = cell[order]
    starts = np.searchsorted(sorted_cells, sorted_cells, side="left")
    rank = np.arange(len(order)) - starts  # position within its cell
    chosen = order[np.lexsort((sorted_cells, rank))][:count]
    return np.sort(chosen)


class KeyframeTracker:
    """Follows one keyframe's points into the frames after it (``start`` at each keyframe, then ``track``)."""

    def __init__(self, max_points: int = 400, max_fb_error_px: float = 1.0):
        self.max_points, self.max_fb_error_px = max_points, max_fb_error_px
        self._gray: np.ndarray | None = None  # the keyframe's (cv2 5's binding takes no prebuilt pyramid)
        self._points = np.zeros((0, 3), np.float32)
        self._pixels = np.zeros((0, 2), np.float32)  # in the keyframe
        self._last = np.zeros((0, 2), np.float32)  # where each was found in the last tracked frame
        self._alive = np.zeros(0, bool)

    @property
    def ready(self) -> bool:
        return self._gray is not None and len(self._points) > 0

    def start(self, gray: np.ndarray, pixels: np.ndarray, points: np.ndarray) -> None:
        """A new keyframe: its grey image, keypoint pixels (N, 2) and colour-camera 3D points (N, 3, NaN without
        depth)."""
        have = np.nonzero(np.isfinite(points[:, 2]))[0]
        keep = have[spread(pixels[have], gray.shape[:2], self.max_points)]
        self._points = points[keep].astype(np.float32)
        self._pixels = pixels[keep].astype(np.float32).reshape(-1, 2)
        self._last = self._pixels.copy()
        self._alive = np.ones(len(keep), bool)
        self._gray = gray

    def predict(self, T_frame_kf: np.ndarray, K: np.ndarray) -> None:
        """Start the next search where a motion prior puts the points: ``T_frame_kf`` takes the keyframe's colour
        camera coordinates to the frame's (points behind the camera or outside the image keep their last pixel)."""
        if not self._alive.any():
            return
        idx = np.nonzero(self._alive)[0]
        X = self._points[idx].astype(np.float64) @ T_frame_kf[:3, :3].T + T_frame_kf[:3, 3]
        z = X[:, 2]
        front = z > 0.05
        uv = np.full((len(idx), 2), np.nan)
        uv[front, 0] = K[0, 0] * X[front, 0] / z[front] + K[0, 2]
        uv[front, 1] = K[1, 1] * X[front, 1] / z[front] + K[1, 2]
        assert self._gray is not None
        h, w = self._gray.shape[:2]
        ok = front & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] <= h - 1)
        self._last[idx[ok]] = uv[ok].astype(np.float32)

    def track(self, gray: np.ndarray) -> Tracks:
        """The keyframe's points found in ``gray`` and checked back (empty when nothing could be tracked)."""
        if self._gray is None or not self._alive.any():
            return Tracks(np.zeros((0, 3), np.float32), np.zeros((0, 2), np.float32))
        idx = np.nonzero(self._alive)[0]
        p0 = self._pixels[idx].reshape(-1, 1, 2)
        guess = self._last[idx].reshape(-1, 1, 2).copy()
        kf, flags = self._gray, cv2.OPTFLOW_USE_INITIAL_FLOW
        p1, st, _ = cv2.calcOpticalFlowPyrLK(
            kf, gray, p0, guess, winSize=WINDOW, maxLevel=LEVELS, criteria=CRITERIA, flags=flags
        )
        p0r, st_r, _ = cv2.calcOpticalFlowPyrLK(
            gray, kf, p1, p0.copy(), winSize=WINDOW, maxLevel=LEVELS, criteria=CRITERIA, flags=flags
        )
        st, st_r = np.asarray(st), np.asarray(st_r)
        fb = np.linalg.norm((np.asarray(p0r) - p0).reshape(-1, 2), axis=1)
        h, w = gray.shape[:2]
        q = np.asarray(p1).reshape(-1, 2)
        ok = (
            (st[:, 0] == 1)
            & (st_r[:, 0] == 1)
            & (fb <= self.max_fb_error_px)
            & (q[:, 0] >= 0)
            & (q[:, 1] >= 0)
            & (q[:, 0] <= w - 1)
            & (q[:, 1] <= h - 1)
        )
        self._alive[idx[~ok]] = False
        self._last[idx[ok]] = q[ok]
        return Tracks(self._points[idx[ok]], q[ok].copy())
