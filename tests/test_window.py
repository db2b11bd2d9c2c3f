"""The bounded iSAM2 window (graph/window.py): the whole graph below the window; past it, a rolled window whose
child process solves the whole graph, and which ends where the whole graph in one iSAM2 does."""

from __future__ import annotations

import os
import signal
from collections import defaultdict
from dataclasses import replace
from itertools import pairwise

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import L, X
from scipy.spatial.transform import Rotation

from bench import building as sim
from evaluation.trajectory_metrics import trajectory_error
from graph.factors import FactorKind, FactorRecord
from graph.geometry import relative
from graph.interface import Graph
from graph.pose_graph import PoseGraph
from graph.settings import GraphSettings
from graph.window import WindowedGraph
from graph.window_factors import FUSE_AT, fused_prior
from service.config import load_settings
from service.node import ServiceNode
from service.persistence import decode, encode, seal, unseal
from service.protocol import encode_frame
from service.replay import frame_publisher
from service.zenoh_session import open_session
from slam.build import build_core
from slam.snapshot import core_state, restore_core
from sources import open_dataset


def _explore(graph, n: int, seed: int = 0, landmarks: int = 40) -> list[np.ndarray]:
    """The ``bench isam2`` building: odometry, Huber loops back to old rooms, landmark observations."""
    rng = np.random.default_rng(seed)
    world = sim.Building.explore(n, landmarks, rng)
    for j in range(len(world.landmarks)):
        graph.add_landmark(j)
    cells: dict = defaultdict(list)
    last_loop = -sim.LOOP_EVERY
    for k, T in enumerate(world.poses):
        seen = sim.in_view(T, world.landmarks, rng) if k % sim.OBSERVE_EVERY == 0 else []
        match = sim.revisit(world.poses, cells, k) if k - last_loop >= sim.LOOP_EVERY else None
        if k == 0:
            graph.add_first(T)
        else:
            graph.add_keyframe(
                sim.noisy(relative(world.poses[k - 1], T), *sim.ODOMETRY_SIGMA, rng), *sim.ODOMETRY_SIGMA
            )
        if seen:
            graph.add_landmark_observations(k, seen, sim.LANDMARK_SIGMA_M)
        if match is not None:
            graph.add_loop(match, k, sim.noisy(relative(world.poses[match], T), *sim.LOOP_SIGMA, rng), *sim.LOOP_SIGMA)
            last_loop = k
        cells[sim.cell(T)].append(k)
    return world.poses


@pytest.fixture
def windowed():
    graphs = []

    def make(window: int, step: int) -> WindowedGraph:
        graphs.append(WindowedGraph(GraphSettings(window_keyframes=window, window_step=step)))
        return graphs[-1]

    yield make
    for g in graphs:
        g.close()


def test_both_graphs_implement_the_graph_interface(windowed):
    assert isinstance(PoseGraph(), Graph) and isinstance(windowed(400, 100), Graph)
    assert not isinstance(object(), Graph)


def test_below_the_window_it_is_the_whole_graph_update_for_update(windowed):
    full, window = PoseGraph(), windowed(400, 100)
    _explore(full, 300)
    _explore(window, 300)
    assert window.start == 0 and window.child is None  # never rolled: no child process
    assert (window.num_keyframes, window.num_factors, window.updates) == (
        full.num_keyframes,
        full.num_factors,
        full.updates,
    )
    np.testing.assert_allclose(window.poses(), full.poses(), atol=1e-9)
    assert window.landmarks().keys() == full.landmarks().keys()
    for j, p in full.landmarks().items():
        np.testing.assert_allclose(window.landmark(j), p, atol=1e-9)
    restored = WindowedGraph.from_state(window.state())
    assert np.array_equal(restored.poses(), window.poses())
    window.flush()  # the end of a run: the batch optimum, where iSAM2 alone stops short
    optimum = _optimum(full)
    assert np.abs(full.poses() - optimum).max() > 10 * np.abs(window.poses() - optimum).max()
    assert np.abs(window.poses() - optimum).max() < 1e-4 and window.child is None
    assert np.array_equal(WindowedGraph.from_state(window.state()).poses(), window.poses())


def _optimum(graph: PoseGraph) -> np.ndarray:
    """The batch Levenberg-Marquardt optimum of a graph's live factors (iSAM2 itself stops short of it)."""
    factors = gtsam.NonlinearFactorGraph()
    for i, f in enumerate(graph.factors):
        if i not in graph.books.removed:
            factors.add(f.to_gtsam())
    values = gtsam.LevenbergMarquardtOptimizer(factors, graph.isam.calculateEstimate()).optimize()
    return np.stack([values.atPose3(X(k)).matrix() for k in range(graph.num_keyframes)])


def test_a_rolled_window_ends_where_the_whole_graph_does(windowed):
    full, window = PoseGraph(), windowed(100, 30)
    truth = np.array(_explore(full, 700))
    _explore(window, 700)
    assert window.start >= 700 - 130 and window.local.num_keyframes <= 130  # the window stayed bounded
    assert window.frozen_landmarks()  # landmarks left the window (and some came back: the loops return to old rooms)
    window.flush()
    assert window.solve_latencies  # the child solved the whole graph
    optimum = _optimum(full)
    off = [np.linalg.norm(g.poses()[:, :3, 3] - optimum[:, :3, 3], axis=1).max() for g in (full, window)]
    assert off[0] < 0.03 and off[1] < 0.005, off  # iSAM2 alone stops 2.2 cm short; the window flushed to it
    ate = [np.sqrt(np.mean(np.linalg.norm(g.poses()[:, :3, 3] - truth[:, :3, 3], axis=1) ** 2)) for g in (full, window)]
    assert ate[1] < 1.05 * ate[0], ate
    for j, p in full.landmarks().items():
        assert np.linalg.norm(window.landmark(j) - p) < 0.05


def _circle() -> tuple[list[np.ndarray], np.ndarray]:
    """True poses of a 200-keyframe circle of radius 5 m back to its start, and an odometry drift per keyframe."""
    true = []
    for i in range(201):
        T = np.eye(4)
        angle = 2 * np.pi * i / 200
        T[:3, :3] = Rotation.from_euler("z", angle).as_matrix()
        T[:3, 3] = [5 * np.cos(angle), 5 * np.sin(angle), 0.0]
        true.append(T)
    drift = np.eye(4)
    drift[:3, :3] = Rotation.from_euler("z", 0.003).as_matrix()
    return true, drift


def test_a_loop_to_a_fixed_keyframe_pulls_the_window_at_once_and_can_be_retracted(windowed):
    """A 200-keyframe circle with drifting odometry; the window holds the last 40-50 keyframes."""
    true, drift = _circle()
    g = windowed(40, 10)
    g.add_first(true[0])
    for a, b in pairwise(true):
        g.add_keyframe(relative(a, b) @ drift, 0.01, 0.5)
    assert g.start > 100
    error = lambda: np.linalg.norm(g.pose(200)[:3, 3] - true[200][:3, 3])
    before = error()
    index = g.add_loop(0, 200, relative(true[0], true[200]), 0.01, 0.5)
    pulled = error()
    assert before > 0.5 and pulled < 0.5 * before  # at once, by the window alone
    g.flush()  # the whole graph spreads the correction over the circle
    assert error() < 0.05 and np.linalg.norm(g.pose(100)[:3, 3] - true[100][:3, 3]) < 0.5
    g.remove_factors([index])
    g.flush()
    assert error() == pytest.approx(before, rel=0.05)


def test_a_rolled_window_restored_from_its_state_continues_like_the_original(windowed):
    g = windowed(60, 20)
    _explore(g, 400, seed=3)
    state = g.state()
    assert state["window"]["start"] > 0
    h = WindowedGraph.from_state(state)
    try:
        assert h.start == g.start and (h.num_keyframes, h.num_factors) == (g.num_keyframes, g.num_factors)
        assert set(h.landmarks()) == set(g.landmarks())
        assert np.array_equal(h.poses(), g.poses())  # the fixed past as it was, the window's iSAM2 replayed
        assert all(np.array_equal(h.landmark(j), p) for j, p in g.landmarks().items())
        step = np.eye(4)
        step[2, 3] = 0.1
        for graph in (g, h):
            graph.add_keyframe(step)
        assert h.start == g.start and np.array_equal(h.poses(), g.poses())  # continues identically until a roll
        for graph in (g, h):
            graph.flush()
        np.testing.assert_allclose(h.poses(), g.poses(), atol=1e-3)  # both at the batch optimum
    finally:
        h.close()


def _run(window: int, step: int):
    settings = load_settings(None, {"graph": {"window_keyframes": window, "window_step": step}})
    ds = open_dataset("synthetic:room?seed=0&frames=300")
    p = build_core(settings)
    try:
        for i in range(len(ds)):
            frame = ds.frame(i)
            frame.odometry = None  # the visual front end: its factors, skip edges and loops go into the graph
            p.step(frame)
        p.finish()
        truth = ds.ground_truth.poses
        return p, trajectory_error(p.trajectory().poses, truth[: len(p.records)]), p.graph.start
    finally:
        p.close()


def test_the_service_pipeline_with_a_small_window_maps_like_the_whole_graph():
    """Visual odometry, loop closures and object landmarks through a 20-keyframe window (the scene's ~100
    keyframes roll it 16 times) end within a millimetre of the whole graph's trajectory error."""
    _, whole_error, whole_start = _run(400, 100)
    small, small_error, small_start = _run(20, 5)
    assert whole_start == 0 and small_start >= 75
    assert small.loops.n_accepted >= 5 and small.graph.num_landmarks >= 3
    assert small.graph.global_solves >= 10
    assert small_error.ate_rmse_m < whole_error.ate_rmse_m + 0.001, (small_error, whole_error)


def test_a_service_snapshot_of_a_rolled_window_restores_the_trajectory_exactly():
    """Through the snapshot format (``encode``, restricted ``decode``): what a SIGKILL'd service resumes from."""
    settings = load_settings(None, {"graph": {"window_keyframes": 20, "window_step": 5}})
    ds = open_dataset("synthetic:room?seed=1&frames=300")
    frames = [ds.frame(i) for i in range(300)]
    for frame in frames:
        frame.odometry = None  # the visual front end, with loop closures
    p = build_core(settings)
    try:
        for frame in frames[:270]:
            p.step(frame)
        p.flush()
        assert p.graph.start > 0 and p.loops.n_accepted > 0
        restored = restore_core(settings, decode(unseal(seal(encode(core_state(p))))))
        try:
            assert restored.graph.start == p.graph.start
            assert np.array_equal(restored.trajectory().poses, p.trajectory().poses)
            assert restored.loop_records() == p.loop_records()
            for frame in frames[270:]:  # and it goes on mapping
                restored.step(frame)
            assert restored.graph.num_keyframes > p.graph.num_keyframes
        finally:
            restored.close()
    finally:
        p.close()


def test_status_shows_where_the_window_starts_and_the_whole_graph_solves():
    """A service over an embedded zenoh session, frames published to it, status read from its summary."""
    settings = load_settings(
        None, {"detector": {"enabled": False}, "robot": "wtest", "graph": {"window_keyframes": 10, "window_step": 3}}
    )
    session = open_session(settings.zenoh, "server", embedded=True)
    node = ServiceNode(settings, session)
    try:
        node.start()
        assert node.status()["graph_window"] == {"first_keyframe": 0, "whole_graph_solves": 0}
        pub = frame_publisher(session, f"{node.prefix}/rgbd")
        data = open_dataset("synthetic:room?seed=0&frames=120&fps=10&width=320&height=240")
        for i in range(len(data)):
            pub.put(encode_frame(data.frame(i)))
            assert node.wait_done(i + 1, timeout=60.0)
        status = node.status()
    finally:
        node.stop()
        session.close()
    assert status["keyframes"] >= 20
    assert status["keyframes"] - 13 <= status["graph_window"]["first_keyframe"] <= status["keyframes"] - 10
    assert status["graph_window"]["whole_graph_solves"] >= 1


def _rolled(windowed, rng, turn_deg: float) -> WindowedGraph:
    """A 4 + 1 keyframe window rolled along 13 keyframes of random small motions."""
    g = windowed(4, 1)
    g.add_first(np.eye(4))
    for _ in range(12):
        g.add_keyframe(sim.noisy(np.eye(4), 0.1, turn_deg, rng))
    assert g.start >= 8
    return g


def test_a_factor_to_a_fixed_keyframe_becomes_a_prior_with_the_same_error(windowed):
    """Both directions, Huber kernel included: the prior's whitened error equals the between-factor's."""
    rng = np.random.default_rng(11)
    g = _rolled(windowed, rng, 5.0)
    fixed, free = g.start - 2, g.start + 1
    for a, b in ((fixed, free), (free, fixed)):
        record = FactorRecord(a, b, sim.noisy(np.eye(4), 0.5, 30.0, rng), 0.02, 1.0, huber_k=3.0)
        prior = g.localize(record, set())
        assert prior.b is None and prior.a == free - g.start
        for _ in range(5):
            T_free = sim.noisy(np.eye(4), 1.0, 40.0, rng)
            values = gtsam.Values()
            values.insert(X(fixed), gtsam.Pose3(g.pose(fixed)))
            values.insert(X(free), gtsam.Pose3(T_free))
            local = gtsam.Values()
            local.insert(X(free - g.start), gtsam.Pose3(T_free))
            assert prior.to_gtsam().error(local) == pytest.approx(record.to_gtsam().error(values), rel=1e-9)


def test_a_landmark_measured_from_a_fixed_keyframe_becomes_a_world_prior_with_the_same_error(windowed):
    """Wider along the viewing ray than across it: the world prior's covariance is the measurement's, rotated."""
    g = _rolled(windowed, np.random.default_rng(12), 30.0)
    fixed = g.start - 2
    record = FactorRecord(fixed, 3, np.array([0.4, -0.2, 2.0]), 0.1, 0.0, None, FactorKind.LANDMARK, range_sigma_m=0.3)
    prior = g.localize(record, {3})
    assert prior.b is None and prior.a == 3 and prior.covariance.shape == (3, 3)
    T = g.pose(fixed)
    landmark = T[:3, :3] @ record.measurement + T[:3, 3]
    errors = {}
    for name, ray in (
        ("along", T[:3, :3] @ record.measurement / np.linalg.norm(record.measurement)),
        ("across", T[:3, :3] @ np.array([1.0, 0.0, -0.2]) / np.linalg.norm([1.0, 0.0, -0.2])),
    ):
        moved = landmark + 0.002 * ray
        values = gtsam.Values()
        values.insert(X(fixed), gtsam.Pose3(T))
        values.insert(L(3), moved)
        local = gtsam.Values()
        local.insert(L(3), moved)
        errors[name] = prior.to_gtsam().error(local)
        assert errors[name] == pytest.approx(record.to_gtsam().error(values), rel=1e-3)
    assert errors["across"] == pytest.approx(9 * errors["along"], rel=0.05)  # sigma 0.1 across, 0.3 along


def test_a_child_that_dies_is_restarted_with_the_whole_history(windowed):
    true, drift = _circle()
    g = windowed(40, 10)
    g.add_first(true[0])
    for k, (a, b) in enumerate(pairwise(true), start=1):
        g.add_keyframe(relative(a, b) @ drift, 0.01, 0.5)
        if k == 120:
            first = g.child
            os.kill(first.pid, signal.SIGKILL)
    g.add_loop(0, 200, relative(true[0], true[200]), 0.01, 0.5)
    g.flush()
    assert first.dead and g.child is not first and g.child_starts == 2
    assert np.linalg.norm(g.pose(200)[:3, 3] - true[200][:3, 3]) < 0.05  # the new child solved the whole loop


def test_waiting_for_an_idle_child_leaves_its_estimate_for_the_next_roll(windowed):
    window = windowed(60, 20)
    _explore(window, 200)
    assert window.start > 0  # rolled: the child is solving the whole graph
    assert window.wait_idle(60)
    child = window._global
    assert child is not None and not child.outstanding
    assert child.receive(0.0) is not None  # the estimate the wait saw come back is still there to take


def test_world_priors_fuse_into_one_with_their_information_summed_and_outliers_weighed_down():
    rng = np.random.default_rng(5)
    truth = np.array([1.0, -0.5, 2.0])
    priors = []
    for _ in range(12):
        a = rng.normal(size=(3, 3))
        covariance = 0.01 * (a @ a.T + np.eye(3))
        priors.append(
            FactorRecord(
                7, None, rng.multivariate_normal(truth, covariance), 0.1, 0.0, None, FactorKind.LANDMARK, covariance
            )
        )
    fused = fused_prior(priors, truth)
    information = sum(np.linalg.inv(f.covariance) for f in priors)
    mean = np.linalg.solve(information, sum(np.linalg.inv(f.covariance) @ f.measurement for f in priors))
    np.testing.assert_allclose(np.linalg.inv(fused.covariance), information, rtol=1e-9)
    np.testing.assert_allclose(fused.measurement, mean, atol=1e-12)
    assert fused.a == 7 and fused.b is None and fused.huber_k is None
    # the same priors robust, with one 2 m off: the fused prior stays with the others
    robust = [replace(f, huber_k=1.345) for f in priors]
    outlier = replace(robust[0], measurement=truth + np.array([2.0, 0.0, 0.0]))
    plain = fused_prior([*priors[1:], replace(outlier, huber_k=None)], truth)
    kept = fused_prior([*robust[1:], outlier], truth)
    assert np.linalg.norm(kept.measurement - truth) < 0.3 * np.linalg.norm(plain.measurement - truth)


def test_a_landmark_seen_from_many_fixed_keyframes_is_one_prior_in_the_window_and_follows_retractions(windowed):
    """A landmark measured from every keyframe of a lap: once those are fixed, the window holds one fused prior
    for them; measurements retracted later leave the window where the whole graph without them is."""
    true, drift = _circle()
    p = np.array([0.0, 0.0, 1.0])
    g, full = windowed(40, 10), PoseGraph()
    measured: list[tuple[int, int]] = []  # (keyframe, factor index) in both graphs
    for graph in (g, full):
        graph.add_landmark(4)
        graph.add_first(true[0])
    for k, (a, b) in enumerate(pairwise(true[:121]), start=1):
        for graph in (g, full):
            graph.add_keyframe(relative(a, b) @ drift, 0.01, 0.5)
        seen = _seen_from(b, p)
        (i,) = g.add_landmark_measurements([(k, 4, seen)], 0.05, 1.345, 0.15)
        (i_full,) = full.add_landmark_measurements([(k, 4, seen)], 0.05, 1.345, 0.15)
        assert i == i_full
        measured.append((k, i))
    assert g.start >= 70 and 4 in g.local.landmarks_in_solver()
    fused = [members for members in g._fused.values() if len(members) > FUSE_AT]
    assert len(fused) == 1 and len(fused[0]) == g.start - 1  # every fixed keyframe's measurement, in one prior
    gone = [i for k, i in measured[5:60:3]]  # retract some of them (a track moved to another object)
    for graph in (g, full):
        graph.remove_factors(gone)
    assert not set(gone) & set(g._to_local)
    assert [len(m) for m in g._fused.values()] == [g.start - 1 - len(gone)]  # the rest fused again
    assert np.linalg.norm(g.landmark(4) - full.landmark(4)) < 0.01  # before any flush: the window's own solve
    g.flush()
    optimum = _optimum(full)
    np.testing.assert_allclose(g.poses()[:, :3, 3], optimum[:, :3, 3], atol=1e-3)
    np.testing.assert_allclose(g.landmark(4), full.optimum()[1][4], atol=1e-3)


def _seen_from(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    Ti = np.linalg.inv(T)
    return Ti[:3, :3] @ p + Ti[:3, 3]


def test_polish_moves_a_window_that_is_the_whole_graph_to_its_batch_optimum_once_per_change(windowed):
    full, window = PoseGraph(), windowed(400, 100)
    _explore(full, 300)
    _explore(window, 300)
    optimum = _optimum(full)
    assert np.abs(window.poses() - optimum).max() > 1e-3  # iSAM2 stops short of it
    assert window.polish() and window.global_solves == 1
    assert np.abs(window.poses() - optimum).max() < 1e-4 and window.child is None
    assert not window.polish()  # nothing added since: nothing to do
    window.add_keyframe(np.eye(4), 0.01, 0.01)
    assert window.polish()


def test_polish_after_a_roll_asks_the_child_and_re_anchors_without_waiting(windowed):
    full, window = PoseGraph(), windowed(100, 30)
    _explore(full, 400)
    _explore(window, 400)
    assert window.start > 0
    solves = window.global_solves
    assert not window.polish()  # asks the child for the batch optimum; does not wait for it
    assert window.wait_idle(120)
    assert window.polish() and window.global_solves == solves + 1
    off = np.linalg.norm(window.poses()[:, :3, 3] - _optimum(full)[:, :3, 3], axis=1).max()
    assert off < 0.005, off
    assert not window.polish()  # polished: nothing added since


def test_a_pose_graph_has_nothing_to_polish():
    graph = PoseGraph()
    _explore(graph, 50)
    before = graph.poses()
    assert not graph.polish() and np.array_equal(graph.poses(), before)
