"""Evaluation of loop-closure policies (dissertation Sec. 3.7, Table 3.1; SPEC 6.9).

Per configuration: ``runs`` runs from random starts that never terminate, each until every loop-closure
location has been tested (a loop closure was due there at least once) or ``max_steps`` passed.
precision = correct loop-closure actions / loop-closure actions taken; recall = correct loop-closure
actions / loop closures due.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from rl.env import GridRules, LoopClosureGrid
from rl.gridmap import GridMap
from rl.policy import Policy


@dataclass
class EvalResult:
    config: str
    policy: str
    runs: int
    lc_due: int
    lc_taken: int
    lc_correct: int
    steps: int  # over all runs
    runs_complete: int  # runs that tested every location before max_steps

    @property
    def precision(self) -> float:
        return self.lc_correct / self.lc_taken if self.lc_taken else 0.0

    @property
    def recall(self) -> float:
        return self.lc_correct / self.lc_due if self.lc_due else 0.0

    def to_json(self) -> dict:
        """The figures ``eval-lc --json`` prints for a configuration (SPEC section 2), and the rest."""
        return {
            "precision": self.precision,
            "recall": self.recall,
            "lc_due": self.lc_due,
            "lc_taken": self.lc_taken,
            "runs": self.runs,
            **{k: v for k, v in asdict(self).items() if k not in ("lc_due", "lc_taken", "runs")},
        }


def evaluate(
    grid: GridMap, policy: Policy, runs: int = 20, seed: int = 10_000, max_steps: int = 20_000, exclude_last: int = 4
) -> EvalResult:
    """Run ``policy`` in ``runs`` non-terminating episodes side by side and count its loop-closure actions."""
    rules = GridRules(exclude_last=exclude_last, terminate=False)
    envs = [LoopClosureGrid(grid, rules) for _ in range(runs)]
    obs = np.stack([env.reset(seed=seed + i)[0] for i, env in enumerate(envs)])
    policy.reset(runs)
    active = np.ones(runs, bool)
    tested: list[set[int]] = [set() for _ in range(runs)]
    due = taken = correct = steps = 0
    for _ in range(max_steps):
        actions = policy.act(obs, envs)
        for i in np.flatnonzero(active):
            obs[i], _, _, _, info = envs[i].step(int(actions[i]))
            steps += 1
            taken += int(actions[i] != 0)
            if info["due"]:
                due += 1
                correct += int(actions[i] == info["correct_action"])
                tested[i].add(info["loop"])
                if len(tested[i]) == grid.n_loops:
                    active[i] = False
            if not active.any():
                break
        if not active.any():
            break
    return EvalResult(grid.name, policy.name, runs, due, taken, correct, steps, int((~active).sum()))
