"""``LoopClosureGrid``: the loop-closure grid world as a gymnasium environment (Sec. 3.5, SPEC 6.9).

The agent moves at random (1 or 2 cells up/down/left/right, never through walls; its heading is its
last motion) and the policy only decides, at each step, whether its current cell is a loop-closure
location it has seen before: action 0 is "no loop closure", action l + 1 is "this is location l".

A loop closure is due when the agent stands on a loop-closure location that it first visited more than
``exclude_last`` (c) steps ago. Rewards (Sec. 3.5.5): +100 for the due location's action, +10 for action
0 when nothing is due, -100 for anything else. Training episodes end with ``terminal_penalty`` after
more than ``max_missed`` consecutive missed loop closures, or after ``max_false`` consecutive
loop-closure actions where none was due; evaluation runs (``terminate=False``) never end.

Each step's ``info`` describes the step just judged: ``due``, ``correct_action``, ``loop`` (location
index or -1), ``cell``, ``cell_action`` (eq. 3.19's i * N + j for the cell acted on) and ``visited``
(bool, one per location: first visited more than c steps ago, i.e. a loop closure would be due there;
the memory the policy must keep, privileged information for the trainer's auxiliary loss).
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from rl.gridmap import GridMap
from rl.vision import HEADINGS, OBS_SIZE, renderer_for

CORRECT_LOOP, CORRECT_NONE, WRONG = 100.0, 10.0, -100.0


@dataclass(frozen=True)
class GridRules:
    """The rules of a loop-closure grid world (SPEC 6.9)."""

    exclude_last: int = 4  # c: visits in the last c steps do not make a loop closure due
    max_missed: int = 4  # training ends after more than this many consecutive missed loop closures
    max_false: int = 3  # ... or after this many consecutive loop-closure actions where none was due
    terminal_penalty: float = -500.0
    max_steps: int = 512  # training episodes are truncated here; 0 = never
    terminate: bool = True  # False: evaluation runs that neither terminate nor truncate


class LoopClosureGrid(gym.Env):
    """Random walk in a grid map; the policy reports loop closures from 84 x 84 cone-of-vision images."""

    # gymnasium reads render modes from this class attribute; Env declares it a plain dict, so no ClassVar
    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}  # noqa: RUF012 -- gymnasium's Env.metadata dict
    observation_space: gym.spaces.Box
    action_space: gym.spaces.Discrete

    def __init__(
        self,
        grid: GridMap | str = "config1",
        rules: GridRules | None = None,
        render_mode: str | None = None,
        **rule_overrides,
    ):
        self.grid = grid if isinstance(grid, GridMap) else GridMap.load(grid)
        self.rules = rules or GridRules(**rule_overrides)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"unsupported render_mode {render_mode!r}")
        self.render_mode = render_mode
        self.renderer = renderer_for(self.grid)
        self.observation_space = gym.spaces.Box(0, 255, (OBS_SIZE, OBS_SIZE, 3), dtype=np.uint8)
        self.action_space = gym.spaces.Discrete(self.grid.n_loops + 1)
        self._loop_index = self.grid.loop_index()
        self._loop_cells = tuple(np.array(self.grid.loops, dtype=np.int64).reshape(-1, 2).T)
        self._free = np.argwhere(~self.grid.walls)
        self._moves = [(h, k) for h in range(4) for k in (1, 2)]
        self.cell = (0, 0)
        self.heading = 0
        self.t = 0

    # ------------------------------------------------------------ gymnasium API

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = options or {}
        if "cell" in options:
            row, col = options["cell"]
            self.cell = (int(row), int(col))
            if self.grid.walls[self.cell]:
                raise ValueError(f"start cell {self.cell} is a wall")
        else:
            row, col = self._free[self.np_random.integers(len(self._free))]
            self.cell = (int(row), int(col))
        self.heading = int(options.get("heading", self.np_random.integers(4)))
        self.t = 0
        self.first_visit = np.full(self.grid.shape, -1, dtype=np.int64)
        self.first_visit[self.cell] = 0
        self.missed = self.false_streak = 0
        return self._observation(), {}

    def step(self, action):
        action = int(action)
        if not self.action_space.contains(action):
            raise ValueError(f"action {action} outside {self.action_space}")
        due = self.loop_due()
        loop = int(self._loop_index[self.cell]) - 1
        correct = self.due_action()
        reward = (CORRECT_LOOP if due else CORRECT_NONE) if action == correct else WRONG
        self.missed = self.missed + 1 if due and action != correct else (0 if due else self.missed)
        self.false_streak = self.false_streak + 1 if (action != 0 and not due) else 0
        info = {
            "due": due,
            "correct_action": correct,
            "loop": loop if loop >= 0 else -1,
            "cell": self.cell,
            "cell_action": self.cell[0] * self.grid.shape[1] + self.cell[1],
            "visited": self.visited(),
        }
        r = self.rules
        terminated = r.terminate and (self.missed > r.max_missed or self.false_streak >= r.max_false)
        if terminated:
            reward += r.terminal_penalty
        self._move()
        truncated = bool(r.terminate and r.max_steps and self.t >= r.max_steps and not terminated)
        return self._observation(), float(reward), bool(terminated), truncated, info

    def render(self):
        if self.render_mode == "rgb_array":
            return self.renderer.full_view(self.cell, self.heading)
        return None

    # ------------------------------------------------------------ world

    def loop_due(self) -> bool:
        """True when the current cell is a loop-closure location first visited more than c steps ago."""
        if self._loop_index[self.cell] == 0:
            return False
        first = self.first_visit[self.cell]
        return bool(0 <= first < self.t - self.rules.exclude_last)

    def visited(self) -> np.ndarray:
        """(n_loops,) bool: location l was first visited more than c steps ago (a loop closure is due there
        whenever the agent stands on it); the same test as ``loop_due``."""
        first = self.first_visit[self._loop_cells]
        return (first >= 0) & (first < self.t - self.rules.exclude_last)

    def due_action(self) -> int:
        """The correct action at the current cell: its location's action when a loop closure is due, else 0."""
        return int(self._loop_index[self.cell]) if self.loop_due() else 0

    def valid_moves(self, cell: tuple[int, int] | None = None) -> list[tuple[int, int]]:
        """(heading, cells) moves from ``cell`` that stay on the grid and cross no wall."""
        r0, c0 = cell or self.cell
        rows, cols = self.grid.shape
        valid = []
        for h, k in self._moves:
            ok = True
            for i in range(1, k + 1):
                r, c = r0 + HEADINGS[h][0] * i, c0 + HEADINGS[h][1] * i
                if not (0 <= r < rows and 0 <= c < cols) or self.grid.walls[r, c]:
                    ok = False
                    break
            if ok:
                valid.append((h, k))
        return valid

    def _move(self) -> None:
        moves = self.valid_moves()
        self.t += 1
        if moves:  # an enclosed cell keeps the agent in place
            h, k = moves[self.np_random.integers(len(moves))]
            self.heading = h
            self.cell = (int(self.cell[0] + HEADINGS[h][0] * k), int(self.cell[1] + HEADINGS[h][1] * k))
        if self.first_visit[self.cell] < 0:
            self.first_visit[self.cell] = self.t

    def _observation(self) -> np.ndarray:
        return self.renderer.observation(self.cell, self.heading)
