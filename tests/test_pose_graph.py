"""iSAM2 pose graph: odometry-only graphs reproduce the chained odometry; covariances grow along the chain."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from graph.pose_graph import FactorRecord, PoseGraph, SolverError


def _step(rng) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.05, 3)).as_matrix()
    T[:3, 3] = rng.normal(0, 0.05, 3)
    return T


def test_odometry_chain_is_reproduced_exactly():
    rng = np.random.default_rng(0)
    start = np.eye(4)
    start[:3, 3] = [1.0, 2.0, 0.5]
    g = PoseGraph()
    g.add_first(start)
    chain = [start]
    for _ in range(300):
        rel = _step(rng)
        g.add_keyframe(rel)
        chain.append(chain[-1] @ rel)
    assert g.num_keyframes == 301 and g.num_factors == 301
    np.testing.assert_allclose(g.poses(), np.stack(chain), atol=1e-9)
    np.testing.assert_allclose(g.pose(150), chain[150], atol=1e-9)


def test_marginal_covariance_grows_with_distance_from_the_prior():
    rng = np.random.default_rng(1)
    g = PoseGraph()
    g.add_first(np.eye(4))
    for _ in range(50):
        g.add_keyframe(_step(rng))
    c1, c50 = g.marginal_covariance(1), g.marginal_covariance(50)
    assert c1.shape == (6, 6)
    assert np.trace(c50[3:, 3:]) > 10 * np.trace(c1[3:, 3:])


def test_loop_closure_pulls_a_drifted_chain_back_and_can_be_retracted():
    true = [np.eye(4)]
    for i in range(1, 41):  # a square loop of 40 keyframes returning to the start
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("z", 2 * np.pi * i / 40).as_matrix()
        T[:3, 3] = [np.cos(2 * np.pi * i / 40) - 1, np.sin(2 * np.pi * i / 40), 0.0]
        true.append(T)
    g = PoseGraph()
    g.add_first(true[0])
    drift = np.eye(4)
    drift[:3, :3] = Rotation.from_euler("z", 0.01).as_matrix()
    for a, b in pairwise(true):
        g.add_keyframe(np.linalg.inv(a) @ b @ drift)
    before = np.linalg.norm(g.pose(40)[:3, 3] - true[40][:3, 3])
    index = g.add_loop(0, 40, np.linalg.inv(true[0]) @ true[40], 0.01, 0.5)
    after = np.linalg.norm(g.pose(40)[:3, 3] - true[40][:3, 3])
    assert before > 0.1 and after < 0.02
    g.remove_factors([index])
    assert np.linalg.norm(g.pose(40)[:3, 3] - true[40][:3, 3]) == pytest.approx(before, rel=0.05)


def _chain(n: int, rng, start: np.ndarray | None = None) -> tuple[PoseGraph, list[np.ndarray]]:
    g = PoseGraph()
    chain = [np.eye(4) if start is None else start]
    g.add_first(chain[0])
    for _ in range(n):
        rel = _step(rng)
        g.add_keyframe(rel)
        chain.append(chain[-1] @ rel)
    return g, chain


def test_a_failed_update_leaves_the_graph_as_before_and_later_keyframes_still_go_in():
    g, chain = _chain(11, np.random.default_rng(2))
    before = g.poses()
    # the shape of update that used to poison iSAM2: a new keyframe's value with a factor iSAM2 rejects
    # (here: to a keyframe that does not exist); iSAM2 kept x12, so every later keyframe failed with
    # "key x12 already exists"
    with pytest.raises(SolverError):
        g.update([FactorRecord(11, 30, np.eye(4), 0.02, 1.0)], [chain[-1]])
    with pytest.raises(SolverError):
        g.add_between(3, 40, np.eye(4), 0.02, 1.0)
    assert (g.num_keyframes, g.num_factors, len(g.factors), g.factorization) == (12, 12, 12, "CHOLESKY")
    assert np.array_equal(g.poses(), before)
    for _ in range(5):
        g.add_keyframe(_step(np.random.default_rng(3)))
    assert g.num_keyframes == 17 and g.pose(16).shape == (4, 4)
    restored = PoseGraph.from_state(g.state())
    assert np.array_equal(restored.poses(), g.poses())


def test_a_long_chain_switches_from_cholesky_to_qr_instead_of_failing():
    g = PoseGraph()
    g.add_first(np.eye(4))
    step = np.eye(4)
    step[0, 3] = 0.1
    for _ in range(2000):  # ~170 m without a loop closure: Cholesky finds the system indeterminant
        g.add_keyframe(step, 0.05, 3.0)
    assert g.factorization == "QR" and g.num_keyframes == 2001 and g.num_factors == 2001
    np.testing.assert_allclose(g.pose(2000)[:3, 3], [200.0, 0.0, 0.0], atol=1e-6)
    restored = PoseGraph.from_state(g.state())
    assert restored.factorization == "QR" and np.array_equal(restored.poses(), g.poses())


def _observe(T_world_cam: np.ndarray, point: np.ndarray) -> np.ndarray:
    return np.linalg.inv(T_world_cam)[:3, :3] @ point + np.linalg.inv(T_world_cam)[:3, 3]


def test_a_landmark_enters_the_solver_once_two_keyframes_observed_it():
    g, chain = _chain(6, np.random.default_rng(4))
    point = chain[0][:3, 3] + np.array([0.3, -0.2, 2.0])
    g.add_landmark(7)
    assert g.add_landmark_observation(7, 0, _observe(chain[0], point), 0.02) is None
    assert g.add_landmark_observation(7, 0, _observe(chain[0], point), 0.02) is None  # same keyframe again
    assert g.num_landmarks == 0 and g.num_factors == 7
    index = g.add_landmark_observation(7, 3, _observe(chain[3], point), 0.02)
    assert index == len(g.factors) - 1 and g.num_landmarks == 1 and g.num_factors == 10
    np.testing.assert_allclose(g.landmark(7), point, atol=1e-6)
    assert g.add_landmark_observation(7, 5, _observe(chain[5], point), 0.02) == index + 1
    np.testing.assert_allclose(g.landmarks()[7], point, atol=1e-6)
    with pytest.raises(ValueError):
        g.add_landmark_observation(8, 0, [0.0, 0.0, 1.0], 0.02)  # never added


def test_a_landmark_with_a_prior_enters_at_once_and_observations_pull_drifted_poses():
    rng = np.random.default_rng(5)
    g = PoseGraph()
    g.add_first(np.eye(4))
    truth, odometry = [np.eye(4)], [np.eye(4)]
    points = {j: np.array([np.cos(j), np.sin(j), 0.5]) * 3.0 for j in range(6)}
    assert g.add_landmark(0, points[0], sigma_m=0.01) and g.num_landmarks == 1
    for j in range(1, 6):
        g.add_landmark(j)
    bias = np.eye(4)
    bias[:3, 3] = [0.01, 0.0, 0.0]  # odometry drifts 1 cm per keyframe
    for k in range(1, 31):
        rel = _step(rng)
        truth.append(truth[-1] @ rel)
        g.add_keyframe(rel @ bias, 0.05, 2.0)
        odometry.append(odometry[-1] @ rel @ bias)
        for j, p in points.items():
            g.add_landmark_observation(j, k, _observe(truth[-1], p), 0.005)
    assert g.num_landmarks == 6
    drift = np.linalg.norm(odometry[-1][:3, 3] - truth[-1][:3, 3])
    error = np.linalg.norm(g.pose(30)[:3, 3] - truth[-1][:3, 3])
    assert drift > 0.2 and error < 0.05
    for j, p in points.items():
        assert np.linalg.norm(g.landmark(j) - p) < 0.05


def test_landmarks_and_waiting_observations_round_trip_through_state():
    from service.persistence import decode, encode, seal, unseal

    g, chain = _chain(8, np.random.default_rng(6))
    points = [np.array([1.0, 0.5, 2.0]), np.array([-1.0, 0.2, 3.0])]
    for j, p in enumerate(points):
        g.add_landmark(j)
        g.add_landmark_observation(j, 2, _observe(chain[2], p), 0.02)
    g.add_landmark_observation(0, 6, _observe(chain[6], points[0]), 0.02)  # landmark 1 is still waiting
    g.add_landmark(2, [0.0, 0.0, 1.0], 0.1)
    h = PoseGraph.from_state(decode(unseal(seal(encode(g.state())))))
    assert np.array_equal(h.poses(), g.poses()) and h.landmarks().keys() == {0, 2}
    assert np.array_equal(h.landmark(0), g.landmark(0))
    for graph in (g, h):  # the waiting observation is kept: a second keyframe inserts landmark 1 in both
        assert graph.add_landmark_observation(1, 7, _observe(chain[7], points[1]), 0.02) == len(graph.factors) - 1
    assert np.array_equal(h.landmark(1), g.landmark(1)) and len(h.factors) == len(g.factors)


def test_a_landmark_whose_observations_are_all_retracted_leaves_the_solver_until_seen_again():
    g, chain = _chain(4, np.random.default_rng(7))
    p = np.array([0.5, 0.5, 2.0])
    g.add_landmark(0)
    g.add_landmark_observation(0, 1, _observe(chain[1], p), 0.02)
    last = g.add_landmark_observation(0, 3, _observe(chain[3], p), 0.02)
    g.remove_factors([last])
    assert g.num_landmarks == 1  # one observation still determines it
    g.remove_factors([last - 1])
    assert g.num_landmarks == 0 and g.landmarks() == {} and g.num_factors == 5
    assert g.add_landmark_observation(0, 2, _observe(chain[2], p), 0.02) is None
    g.add_landmark_observation(0, 4, _observe(chain[4], p), 0.02)
    np.testing.assert_allclose(g.landmark(0), p, atol=1e-6)
    h = PoseGraph.from_state(g.state())
    assert np.array_equal(h.landmark(0), g.landmark(0)) and h.num_landmarks == 1


def _circle_around_an_object(range_sigma_m: float | None) -> float:
    """Keyframes on a 1.5 m circle looking at an object at the origin, exact odometry (2 cm / 1 deg), and
    each view's measurement of the object 0.15 m short of its centre (the visible surface's centroid) with a
    0.1 m sigma. Returns the mean distance of the optimised keyframes from the origin minus 1.5 m."""
    poses = []
    for a in np.linspace(0.0, 2 * np.pi, 24, endpoint=False):
        position = 1.5 * np.array([np.cos(a), np.sin(a), 0.0])
        z = -position / 1.5  # the camera looks at the origin
        x = np.cross([0.0, 0.0, 1.0], z)
        T = np.eye(4)
        T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
        T[:3, 3] = position
        poses.append(T)
    g = PoseGraph()
    g.add_first(poses[0])
    g.add_landmark(0)
    for k, T in enumerate(poses):
        if k:
            g.add_keyframe(np.linalg.inv(poses[k - 1]) @ T, 0.02, 1.0)
        centre = (np.linalg.inv(T) @ np.r_[0.0, 0.0, 0.0, 1.0])[:3]
        g.add_landmark_measurements([(k, 0, centre * (1 - 0.15 / np.linalg.norm(centre)))], 0.1, None, range_sigma_m)
    return float(np.mean(np.linalg.norm(g.poses()[:, :3, 3], axis=1)) - 1.5)


def test_a_wider_range_sigma_keeps_biased_object_measurements_from_shrinking_the_map():
    """The visible surface's centroid lies short of the object's centre in every view: with an isotropic
    sigma the views pull the cameras in; with the range sigma 3 x wider, much less."""
    isotropic, ranged = _circle_around_an_object(None), _circle_around_an_object(0.3)
    assert isotropic < -0.02
    assert abs(ranged) < abs(isotropic) / 3


def test_range_sigmas_and_rotated_landmark_priors_round_trip_through_the_factor_columns():
    from graph.factors import FactorKind, from_columns, position_covariance, to_columns

    R = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    records = [
        FactorRecord(2, 0, np.array([0.5, 0.1, 2.0]), 0.1, 0.0, 1.345, FactorKind.LANDMARK, range_sigma_m=0.3),
        FactorRecord(
            0,
            None,
            np.array([1.0, 2.0, 0.5]),
            0.1,
            0.0,
            None,
            FactorKind.LANDMARK,
            R @ position_covariance(np.array([0.5, 0.1, 2.0]), 0.1, 0.3) @ R.T,
        ),
        FactorRecord(1, None, np.array([1.0, 2.0, 0.5]), 0.1, 0.0, None, FactorKind.LANDMARK),
        FactorRecord(0, 1, np.eye(4), 0.02, 1.0),
    ]
    back = from_columns(to_columns(records))
    for r, b in zip(records, back, strict=True):
        assert (b.a, b.b, b.kind, b.huber_k, b.range_sigma_m) == (r.a, r.b, r.kind, r.huber_k, r.range_sigma_m)
        assert np.array_equal(b.measurement, r.measurement)
        assert (b.covariance is None) == (r.covariance is None)
        if r.covariance is not None:
            assert np.allclose(b.covariance, r.covariance, atol=0)


# The payload of a snapshot holding {"records": [...]}, written by release 0.1.0's ``service.persistence.encode``
# with its ``FactorRecord``s (an int ``kind``, ``b`` = -1 on a prior): a pose prior, a Huber between-factor, a
# landmark prior and a landmark measurement with a range sigma.
RECORDS_V0_1_0 = (
    "MwIAAAAAAAAEAAAAAAAAAIAAAAAAAAAAgAAAAAAAAAAYAAAAAAAAABgAAAAAAAAAgAWVKAIAAAAAAAB9lCiMBmZvcm1hdJRLAYwF"
    "c3RhdGWUfZSMB3JlY29yZHOUXZQojA1ncmFwaC5mYWN0b3JzlIwMRmFjdG9yUmVjb3JklJOUKYGUfZQojAFhlEsAjAFilEr/////"
    "jAttZWFzdXJlbWVudJSME251bXB5Ll9jb3JlLm51bWVyaWOUjAtfZnJvbWJ1ZmZlcpSTlCiXjAVudW1weZSMBWR0eXBllJOUjAJm"
    "OJSJiIeUUpQoSwOMATyUTk5OSv////9K/////0sAdJRiSwRLBIaUjAFDlHSUUpSMB3NpZ21hX22URz8aNuLrHEMtjAlzaWdtYV9k"
    "ZWeURz+EeuFHrhR7jAdodWJlcl9rlE6MBGtpbmSUSwCMCmNvdmFyaWFuY2WUTowNcmFuZ2Vfc2lnbWFfbZROdWJoCCmBlH2UKGgL"
    "SwBoDEsBaA1oECiXaBZLBEsEhpRoGnSUUpRoHUc/lHrhR64Ue2geRz/wAAAAAAAAaB9HQAgAAAAAAABoIEsAaCFOaCJOdWJoCCmB"
    "lH2UKGgLSwRoDEr/////aA1oECiXaBZLA4WUaBp0lFKUaB1HP7mZmZmZmZpoHkcAAAAAAAAAAGgfTmggSwFoIU5oIk51YmgIKYGU"
    "fZQoaAtLAWgMSwRoDWgQKJdoFksDhZRoGnSUUpRoHUc/uZmZmZmZmmgeRwAAAAAAAAAAaB9HP/WFHrhR64VoIEsBaCFOaCJHP9Mz"
    "MzMzMzN1YmVzdS4AAAAAAADwPwAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAA8D8AAAAAAAAAAAAAAAAAAAAA"
    "AAAAAAAAAAAAAAAAAAAAAAAAAAAAAPA/AAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAADwPwAAAAAAAPA/AAAA"
    "AAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAADwPwAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAA"
    "8D8AAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAPA/AAAAAAAA8D8AAAAAAAAAQAAAAAAAAOA/AAAAAAAA4D+a"
    "mZmZmZm5PwAAAAAAAABA"
)


def test_factor_records_pickled_by_release_0_1_0_restore_with_kinds_and_no_second_end():
    import base64

    from graph.factors import FactorKind
    from service.persistence import decode

    old = decode(base64.b64decode(RECORDS_V0_1_0))["records"]
    expected = [
        FactorRecord(0, None, np.eye(4), 1e-4, 0.01),
        FactorRecord(0, 1, np.eye(4), 0.02, 1.0, 3.0),
        FactorRecord(4, None, np.array([1.0, 2.0, 0.5]), 0.1, 0.0, None, FactorKind.LANDMARK),
        FactorRecord(1, 4, np.array([0.5, 0.1, 2.0]), 0.1, 0.0, 1.345, FactorKind.LANDMARK, range_sigma_m=0.3),
    ]
    assert len(old) == len(expected)
    for r, e in zip(old, expected, strict=True):
        assert type(r.kind) is FactorKind
        assert (r.a, r.b, r.sigma_m, r.sigma_deg, r.huber_k, r.kind, r.covariance, r.range_sigma_m) == (
            e.a,
            e.b,
            e.sigma_m,
            e.sigma_deg,
            e.huber_k,
            e.kind,
            e.covariance,
            e.range_sigma_m,
        )
        assert np.array_equal(r.measurement, e.measurement)
        factor, wanted = r.to_gtsam(), e.to_gtsam()  # a prior where b was -1
        assert type(factor) is type(wanted) and list(factor.keys()) == list(wanted.keys())


def test_factor_records_round_trip_through_the_snapshot_format_kinds_included():
    from graph.factors import FactorKind
    from service.persistence import decode, encode, seal, unseal

    records = [
        FactorRecord(3, None, np.array([1.0, 2.0, 0.5]), 0.1, 0.0, None, FactorKind.LANDMARK, 0.01 * np.eye(3)),
        FactorRecord(0, 2, np.eye(4), 0.02, 1.0, 3.0),
    ]
    back = decode(unseal(seal(encode({"records": records}))))["records"]
    for r, b in zip(records, back, strict=True):
        assert (b.a, b.b, b.kind, b.huber_k) == (r.a, r.b, r.kind, r.huber_k) and type(b.kind) is FactorKind
        assert np.array_equal(b.measurement, r.measurement)
        assert (b.covariance is None) == (r.covariance is None)
        assert r.covariance is None or np.array_equal(b.covariance, r.covariance)


def test_factor_columns_without_kinds_are_pose_factors_and_minus_one_is_a_prior():
    from graph.factors import FactorKind, from_columns

    columns = {  # the columns of a snapshot from before landmarks
        "a": np.array([0, 0]),
        "b": np.array([-1, 1]),
        "measurement": np.stack([np.eye(4), np.eye(4)]),
        "sigma_m": np.array([1e-4, 0.02]),
        "sigma_deg": np.array([0.01, 1.0]),
        "huber_k": np.array([np.nan, 3.0]),
    }
    prior, between = from_columns(columns)
    assert (prior.b, prior.kind, prior.huber_k, between.b, between.kind, between.huber_k) == (
        None,
        FactorKind.POSE,
        None,
        1,
        FactorKind.POSE,
        3.0,
    )


def test_the_graph_settings_are_the_configuration_section_frozen_and_strict():
    import pydantic

    from graph.settings import GraphSettings
    from service.config import ConfigError, load_settings

    settings = load_settings(None, {"graph": {"window_keyframes": 20, "odometry_sigma_m": 0.05}}).graph
    assert type(settings) is GraphSettings and (settings.window_keyframes, settings.odometry_sigma_m) == (20, 0.05)
    assert settings.partial_relinearization_check and PoseGraph(settings).settings is settings
    with pytest.raises(pydantic.ValidationError):
        settings.window_step = 3
    with pytest.raises(ConfigError, match="graph"):
        load_settings(None, {"graph": {"window_size": 20}})
    with pytest.raises(ConfigError, match=r"graph\.window_keyframes"):
        load_settings(None, {"graph": {"window_keyframes": 1}})
