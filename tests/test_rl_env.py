"""The loop-closure grid world: maps, motion, cone of vision, rewards, termination, seeding (SPEC 6.9)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import rl
from rl.env import CORRECT_LOOP, CORRECT_NONE, WRONG, GridRules, LoopClosureGrid
from rl.evaluate import evaluate
from rl.gridmap import SHIPPED, GridMap, MapError
from rl.policy import NoLoopPolicy, OraclePolicy, RandomPolicy
from rl.vision import AGENT, HEADINGS, visible_cells


def open_map(rows: int = 7, cols: int = 7, walls=(), loops=((1, 1), (5, 5)), features=()) -> GridMap:
    w = np.zeros((rows, cols), bool)
    for cell in walls:
        w[cell] = True
    return GridMap("test", w, tuple(tuple(b) for b in features), tuple(loops))


def test_registered_env_passes_check_env():
    env = gym.make(rl.ENV_ID, grid="config2", render_mode="rgb_array")
    check_env(env.unwrapped, skip_render_check=False)
    assert env.action_space.n == 5
    assert env.observation_space.shape == (84, 84, 3)


def test_shipped_configurations_match_table_3_1():
    sizes = {g: (GridMap.load(g).shape, GridMap.load(g).n_loops) for g in SHIPPED}
    assert sizes == {
        "config1": ((10, 10), 2),
        "config2": ((10, 10), 4),
        "config3": ((10, 10), 5),
        "config4": ((10, 10), 8),
        "config5": ((15, 15), 14),
        "config6": ((84, 84), 20),
    }
    for name in SHIPPED:
        g = GridMap.load(name)
        assert len(g.features) >= 8 and len({cell for b in g.features for cell in b}) == sum(map(len, g.features))


def test_map_file_round_trip_and_validation(tmp_path):
    g = GridMap.load("config3")
    path = g.save(tmp_path / "m.json")
    again = GridMap.load(path)
    assert np.array_equal(again.walls, g.walls) and again.features == g.features and again.loops == g.loops
    with pytest.raises(MapError, match="wall"):
        open_map(walls=[(1, 1)])
    with pytest.raises(MapError, match="outside"):
        open_map(loops=[(9, 9)])


def test_seeded_rollouts_are_deterministic():
    def rollout(seed):
        env = LoopClosureGrid("config4")
        obs, _ = env.reset(seed=seed)
        cells = [env.cell]
        for a in [0, 1, 0, 0, 2, 0] * 10:
            obs, r, term, trunc, _ = env.step(a)
            cells.append((env.cell, env.heading, r, term))
            if term or trunc:
                break
        return cells, obs

    a, b, c = rollout(7), rollout(7), rollout(8)
    assert a[0] == b[0] and np.array_equal(a[1], b[1])
    assert a[0] != c[0]


def test_random_walk_moves_one_or_two_cells_never_through_walls():
    env = LoopClosureGrid("config5", rules=GridRules(terminate=False))
    env.reset(seed=3)
    walls = env.grid.walls
    for _ in range(3000):
        before = env.cell
        env.step(0)
        d = np.subtract(env.cell, before)
        steps = int(np.abs(d).sum())
        assert steps in (1, 2) and (d[0] == 0 or d[1] == 0), (before, env.cell)
        assert tuple(d // steps) == tuple(HEADINGS[env.heading])  # heading = the last motion
        for i in range(1, steps + 1):  # every cell passed is free
            assert not walls[before[0] + HEADINGS[env.heading][0] * i, before[1] + HEADINGS[env.heading][1] * i]


def test_cone_covers_60_degrees_and_walls_occlude():
    walls = np.zeros((9, 9), bool)
    walls[4, 5] = True
    seen = visible_cells(walls, (4, 1), heading=1)  # looking right along row 4
    assert seen[4, 4] and seen[4, 5]  # free cell before the wall, and the wall itself
    assert not seen[4, 6] and not seen[4, 8]  # behind the wall
    assert seen[2, 8]  # 2 rows off over 7 columns: 16 degrees, clear line
    assert not seen[0, 3]  # 63 degrees off the heading
    assert not seen[4, 0]  # behind the agent
    assert seen[4, 1]  # its own cell
    open_seen = visible_cells(np.zeros((9, 9), bool), (4, 1), heading=1)
    angles = [
        np.degrees(np.arctan2(abs(r - 4), c - 1))
        for r, c in zip(*np.nonzero(open_seen), strict=True)
        if (r, c) != (4, 1)
    ]
    assert max(angles) <= 30.0 + 1e-9 and min(angles) == 0.0


def test_observation_shows_agent_and_only_what_it_sees():
    env = LoopClosureGrid(open_map(walls=[(3, 4)]))
    obs, _ = env.reset(seed=0, options={"cell": (3, 1), "heading": 1})
    assert obs.shape == (84, 84, 3) and obs.dtype == np.uint8
    px = 84 / 7
    centre = lambda r, c: obs[int((r + 0.5) * px), int((c + 0.5) * px)]
    assert tuple(centre(3, 1)) == AGENT
    assert tuple(centre(3, 4)) == (255, 255, 255)  # the wall is seen
    assert tuple(centre(3, 6)) == (0, 0, 0)  # occluded behind it
    assert tuple(centre(0, 1)) == (0, 0, 0)  # outside the cone
    env.render_mode = "rgb_array"
    assert env.render().ndim == 3


def _place(env: LoopClosureGrid, cell, t: int, first_visit: int | None):
    env.cell, env.t = cell, t
    env.first_visit[:] = -1
    if first_visit is not None:
        env.first_visit[cell] = first_visit


def test_reward_table_and_due_rule_with_last_c_exclusion():
    env = LoopClosureGrid(open_map(), rules=GridRules(exclude_last=4, terminate=False))
    env.reset(seed=0)
    loop2 = (5, 5)  # location index 1 -> action 2
    cases = [  # (first visit, action, expected reward, due)
        (10, 2, CORRECT_LOOP, True),
        (10, 0, WRONG, True),
        (10, 1, WRONG, True),
        (15, 2, CORRECT_LOOP, True),
        (16, 2, WRONG, False),
        (16, 0, CORRECT_NONE, False),  # t=20, c=4: 15 < 16
        (20, 0, CORRECT_NONE, False),  # first visit now
    ]
    for first, action, reward, due in cases:
        _place(env, loop2, 20, first)
        _, r, _, _, info = env.step(action)
        assert (r, info["due"]) == (reward, due), (first, action)
        if due:
            assert info["correct_action"] == 2 and info["cell_action"] == 5 * 7 + 5
    _place(env, (3, 3), 20, 1)  # visited before, but not a loop-closure location
    assert env.step(0)[1] == CORRECT_NONE
    _place(env, (3, 3), 20, 1)
    assert env.step(1)[1] == WRONG


def test_episode_ends_after_five_missed_loop_closures_or_three_false_ones():
    env = LoopClosureGrid(open_map(), rules=GridRules(terminal_penalty=-500.0))
    env.reset(seed=0)
    for i in range(5):
        _place(env, (1, 1), 50 + i * 10, 0)
        env.missed = i
        _, r, term, _, _ = env.step(0)
    assert term and r == WRONG - 500.0 and env.missed == 5
    env.reset(seed=0)
    outcomes = []
    for i in range(3):
        _place(env, (3, 3), 10 + i, 0)
        outcomes.append(env.step(1)[2])
    assert outcomes == [False, False, True]
    evaluation = LoopClosureGrid(open_map(), rules=GridRules(terminate=False))
    evaluation.reset(seed=0)
    for _ in range(2000):  # always wrong, never terminates nor truncates
        _, _, term, trunc, _ = evaluation.step(1)
        assert not term and not trunc


def test_training_episodes_truncate_at_max_steps():
    env = LoopClosureGrid("config1", rules=GridRules(max_steps=50))
    env.reset(seed=1)
    oracle = OraclePolicy()
    for _ in range(50):
        _, _, term, trunc, _ = env.step(int(oracle.act(None, [env])[0]))
        assert not term
    assert trunc


def test_evaluation_baselines_bound_the_task():
    grid = GridMap.load("config2")
    oracle = evaluate(grid, OraclePolicy(), runs=5, seed=1)
    assert oracle.runs_complete == 5 and oracle.lc_due > 0
    assert oracle.precision == 1.0 and oracle.recall == 1.0
    silent = evaluate(grid, NoLoopPolicy(), runs=5, seed=1)
    assert silent.lc_taken == 0 and silent.recall == 0.0 and silent.lc_due == oracle.lc_due  # same walks
    rand = evaluate(grid, RandomPolicy(0), runs=5, seed=1)
    assert rand.precision < 0.2 and 0.05 < rand.recall < 0.5  # 1 in 5 actions is right when one is due


def test_visited_info_is_the_memory_that_decides_due():
    """A scripted walk (the env's own motion, restricted to one move at a time) with c = 4."""
    env = LoopClosureGrid(open_map(), rules=GridRules(exclude_last=4, terminate=False))  # loops (1, 1), (5, 5)
    env.reset(seed=0, options={"cell": (1, 1), "heading": 1})
    up, right, down, left = 0, 1, 2, 3
    script = [
        (right, 2),
        (right, 2),
        (down, 2),
        (down, 2),  # t = 4: first visit of location 1 at (5, 5)
        (up, 1),
        (down, 1),  # t = 6: back at (5, 5) within the last c steps
        (left, 2),
        (up, 2),
        (up, 2),
        (left, 2),  # t = 10: back at (1, 1), first visited at t = 0
        (right, 2),
        (right, 2),
        (down, 2),
        (down, 2),  # t = 14: (5, 5) again, first visit 4 < 14 - 4
        (left, 1),
    ]
    infos = []
    for move in script:
        env.valid_moves = lambda cell=None, move=move: [move]
        infos.append(env.step(0)[4])
    infos.append(env.step(0)[4])
    visited = np.array([info["visited"] for info in infos])
    assert visited.shape == (16, 2) and visited.dtype == bool
    # location 0: first visit t = 0, remembered from t = 5; location 1: first visit t = 4, from t = 9
    assert visited[:, 0].tolist() == [t >= 5 for t in range(16)]
    assert visited[:, 1].tolist() == [t >= 9 for t in range(16)]
    assert [info["cell"] for info in infos[:5]] == [(1, 1), (1, 3), (1, 5), (3, 5), (5, 5)]
    assert [t for t, info in enumerate(infos) if info["due"]] == [10, 14]
    assert [t for t, info in enumerate(infos) if info["loop"] >= 0] == [0, 4, 6, 10, 14]
    for info in infos:  # due exactly where the agent stands on a location it remembers
        assert info["due"] == (info["loop"] >= 0 and bool(info["visited"][info["loop"]]))
    env.reset(seed=1)
    assert not env.step(0)[4]["visited"].any()  # a new episode remembers nothing


def test_visited_info_agrees_with_the_walk_in_a_long_random_run():
    env = LoopClosureGrid("config4", rules=GridRules(exclude_last=4, terminate=False))
    env.reset(seed=5)
    loops = env.grid.loops
    first: dict = {}
    for t in range(1500):
        first.setdefault(env.cell, t)
        info = env.step(int(env.due_action()))[4]
        expected = [cell in first and first[cell] < t - 4 for cell in loops]
        assert info["visited"].tolist() == expected, t
        assert info["due"] == (info["loop"] >= 0 and expected[info["loop"]])
    assert all(info["visited"])  # 1500 steps visit every location of a 10 x 10 map
