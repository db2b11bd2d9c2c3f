"""RGB-D odometry: relative poses on synthetic pairs, ICP, unregistered depth, tracking loss, real-data ATE."""

from __future__ import annotations

import math

import numpy as np
import pytest

from graph.geometry import motion_magnitude, relative
from perception.frontend import VisualOdometry
from perception.icp import icp_refine
from perception.keyframing import KeyframeSettings
from perception.odometry import FeatureExtractor, OdometrySettings, RelativePoseEstimator
from perception.registration import depth_at_color_pixels, depth_in_color
from sources import open_dataset
from tests.conftest import REDKITCHEN, requires_redkitchen

SPEC = "synthetic:room?seed=0&frames=300"


@pytest.fixture(scope="module")
def room():
    return open_dataset(SPEC)


@pytest.mark.parametrize("i,j", [(10, 13), (100, 104), (200, 202)])
def test_pnp_recovers_true_relative_pose_on_synthetic_pairs(room, i, j):
    fe, est = FeatureExtractor(room.camera), RelativePoseEstimator(room.camera)
    rel = est.estimate(fe.extract(room.frame(i)), fe.extract(room.frame(j)))
    gt = room.ground_truth.poses
    dt, dr = motion_magnitude(relative(relative(gt[i], gt[j]), rel.T_a_b))
    assert dt < 0.01 and math.degrees(dr) < 0.5
    assert rel.inliers > 100 and rel.residual_px < 2.0


def test_icp_refines_a_perturbed_pose_on_exact_depth(room):
    gt = room.ground_truth.poses
    a, b = room.frame(50), room.frame(53)
    true = relative(gt[50], gt[53])
    start = true.copy()
    start[:3, 3] += [0.01, -0.008, 0.005]
    result = icp_refine(b.depth_m(), a.depth_m(), room.camera.depth, start)
    assert result is not None
    dt, dr = motion_magnitude(relative(true, result.T))
    assert dt < 0.004 and math.degrees(dr) < 0.3


def test_visual_odometry_tracks_a_synthetic_segment_within_centimetres(room):
    vo = VisualOdometry(room.camera, KeyframeSettings())
    gt = room.ground_truth.poses
    poses = [vo.track(room.frame(i)).pose for i in range(0, 60)]
    drift, _ = motion_magnitude(relative(relative(gt[0], gt[59]), poses[59]))
    assert vo.lost_count == 0 and drift < 0.03


def test_a_textureless_frame_is_tracked_by_depth_icp(room):
    vo = VisualOdometry(room.camera, KeyframeSettings())
    vo.track(room.frame(0))
    blank = room.frame(3)
    blank.rgb[:] = 128  # no feature at all: the fallback chain poses it from the depth
    step = vo.track(blank)
    assert not step.lost and step.keyframe and step.method == "icp"
    gt = room.ground_truth.poses
    dt, dr = motion_magnitude(relative(relative(gt[0], gt[3]), step.pose))
    assert dt < 0.01 and math.degrees(dr) < 0.5
    assert step.sigma_m == vo.config.icp_sigma_m


def test_without_texture_or_fallback_tracking_is_lost_without_an_invented_factor(room):
    vo = VisualOdometry(room.camera, KeyframeSettings(), OdometrySettings(fallback=False))
    vo.track(room.frame(0))
    blank = room.frame(1)
    blank.rgb[:] = 128
    step = vo.track(blank)  # nothing to track from: no pose, no keyframe, the keyframe stays
    assert step.lost and not step.posed and not step.keyframe and step.factor is None and step.method == "lost"
    assert not vo.track(room.frame(2)).lost and vo.lost_count == 1  # tracked against keyframe 0 again
    step = vo.track(room.frame(150))  # half a turn away: texture, but nothing in common
    assert step.lost and step.posed and step.keyframe and step.factor is None and vo.lost_count == 2
    assert not vo.track(room.frame(152)).lost  # tracking re-initialised on the lost frame


@requires_redkitchen
def test_depth_lookup_at_colour_pixels_agrees_with_full_registration():
    ds = open_dataset(str(REDKITCHEN))
    f = ds.frame(3)
    dm = f.depth_m()
    full = depth_in_color(dm, ds.camera)
    px = np.random.default_rng(0).uniform([0, 0], [639, 479], (3000, 2))
    fast = depth_at_color_pixels(px, dm, ds.camera)
    ref = full[np.round(px[:, 1]).astype(int), np.round(px[:, 0]).astype(int)]
    ok = np.isfinite(fast) & np.isfinite(ref)
    assert ok.mean() > 0.5
    assert np.mean(np.abs(fast[ok] - ref[ok]) < 0.02) > 0.9


@requires_redkitchen
def test_visual_odometry_on_a_real_7scenes_segment_has_small_ate():
    from evaluation.trajectory_metrics import trajectory_error

    ds = open_dataset(str(REDKITCHEN))
    vo = VisualOdometry(ds.camera, KeyframeSettings())
    n = 120
    poses = np.stack([vo.track(ds.frame(i)).pose for i in range(n)])
    err = trajectory_error(poses, ds.ground_truth.poses[:n])
    assert vo.lost_count == 0
    assert err.ate_rmse_m < 0.03, err.ate_rmse_m
