"""Loop-closure policies that act in the grid world: the trained one (ONNX, no torch) and baselines.

Every policy acts on a batch of environments at once: ``act(obs, envs)`` takes (B, 84, 84, 3) images
and returns B actions. Recurrent policies keep one LSTM state per environment slot.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Protocol

import numpy as np
import onnxruntime as ort

from rl.env import LoopClosureGrid
from rl.gridmap import GridMap


class Policy(Protocol):
    name: str

    def reset(self, n: int) -> None: ...

    def act(self, obs: np.ndarray, envs: Sequence[LoopClosureGrid]) -> np.ndarray: ...


class OnnxPolicy:
    """A trained actor exported to ONNX: probabilities and LSTM state per step, on onnxruntime.

    Beside ``FILE.onnx`` lies ``FILE.json``: the map it was trained for, its LSTM size and training figures.
    """

    name = "policy"

    def __init__(self, path: str | Path, threads: int = 1):
        self.path = Path(path)
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        self.session = ort.InferenceSession(str(self.path), options, providers=["CPUExecutionProvider"])
        self.meta = json.loads(self.path.with_suffix(".json").read_text())
        self.grid = GridMap.from_json(self.meta["map"])
        self.hidden = int(self.meta["hidden"])
        self.h = self.c = np.zeros((0, self.hidden), np.float32)

    def reset(self, n: int) -> None:
        self.h = np.zeros((n, self.hidden), np.float32)
        self.c = np.zeros((n, self.hidden), np.float32)

    def probabilities(self, obs: np.ndarray) -> np.ndarray:
        """Advance the LSTM state by one step and return (B, n_actions) action probabilities."""
        probs, self.h, self.c = self.session.run(
            None, {"obs": np.ascontiguousarray(obs, np.uint8), "h": self.h, "c": self.c}
        )
        return probs

    def act(self, obs: np.ndarray, envs: Sequence[LoopClosureGrid] = ()) -> np.ndarray:
        return self.probabilities(obs).argmax(axis=1)


class RandomPolicy:
    """Uniform over all actions."""

    name = "random"

    def __init__(self, seed: int = 0):
        self.rng = np.random.default_rng(seed)

    def reset(self, n: int) -> None:
        pass

    def act(self, obs: np.ndarray, envs: Sequence[LoopClosureGrid]) -> np.ndarray:
        return np.array([self.rng.integers(env.action_space.n) for env in envs])


class NoLoopPolicy:
    """Never reports a loop closure."""

    name = "no-loop-closure"

    def reset(self, n: int) -> None:
        pass

    def act(self, obs: np.ndarray, envs: Sequence[LoopClosureGrid]) -> np.ndarray:
        return np.zeros(len(envs), dtype=np.int64)


class OraclePolicy:
    """Perfect memory of where the agent has been: the upper bound (reads the environment's state)."""

    name = "oracle"

    def reset(self, n: int) -> None:
        pass

    def act(self, obs: np.ndarray, envs: Sequence[LoopClosureGrid]) -> np.ndarray:
        return np.array([env.due_action() for env in envs])
