"""Experience collection for PPO (rl/ppo.py): the synchronous actors (a gymnasium vector environment), the
per-step rollout buffer, and the helpers that read the vector environment's info and pack observations."""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch

from rl.env import GridRules, LoopClosureGrid
from rl.gridmap import GridMap
from rl.train_config import TrainConfig


@dataclass
class Buffer:
    """Per-step rollout storage, (T, n_envs) leading dimensions; LSTM states are those before the step."""

    obs: np.ndarray
    starts: np.ndarray
    actions: np.ndarray
    logprobs: np.ndarray
    rewards: np.ndarray
    dones: np.ndarray
    targets: np.ndarray
    at_loop: np.ndarray  # the agent stood on a loop-closure location
    loop: np.ndarray  # the location's index, -1 for none
    visited: np.ndarray  # (T, n_envs, n_loops) env info "visited": the auxiliary loss's targets
    states: np.ndarray  # (T, 4, n_envs, hidden): actor h, c, critic h, c
    filled: int = 0

    @classmethod
    def empty(cls, T: int, n: int, hidden: int, n_loops: int) -> Buffer:
        return cls(
            np.zeros((T, n, 84, 84, 3), np.uint8),
            np.zeros((T, n), bool),
            np.zeros((T, n), np.int64),
            np.zeros((T, n), np.float32),
            np.zeros((T, n), np.float32),
            np.zeros((T, n), bool),
            np.zeros((T, n), np.int64),
            np.zeros((T, n), bool),
            np.full((T, n), -1, np.int64),
            np.zeros((T, n, n_loops), bool),
            np.zeros((T, 4, n, hidden), np.float32),
        )

    def drop_front(self, n: int) -> None:
        """Keep steps [n, filled) as the start of the next batch."""
        keep = self.filled - n
        for name in (
            "obs",
            "starts",
            "actions",
            "logprobs",
            "rewards",
            "dones",
            "targets",
            "at_loop",
            "loop",
            "visited",
            "states",
        ):
            arr = getattr(self, name)
            arr[:keep] = arr[n : self.filled].copy()
        self.filled = keep


def distinct_frames(obs: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """(T, B, 84, 84, 3) images -> the distinct images and, per step, the index of its image.

    A grid world has few distinct views (cells x headings), so the encoder runs on each once.
    """
    T, B = obs.shape[:2]
    flat = np.ascontiguousarray(obs.reshape(T * B, -1))
    _, first, inverse = np.unique(
        flat.view(np.dtype((np.void, flat.shape[1]))).ravel(), return_index=True, return_inverse=True
    )
    return torch.from_numpy(flat[first].reshape(-1, *obs.shape[2:])), torch.from_numpy(inverse.reshape(T, B))


def step_info(info: dict, key: str, done: np.ndarray) -> np.ndarray:
    """A vector env's per-step info field; with same-step autoreset, finished actors report it in final_info."""
    if key in info:
        values = np.array(info[key])
    elif done.any():  # every actor finished: the shape of the field comes from final_info
        values = np.zeros_like(np.array(info["final_info"][key]))
    else:
        values = np.zeros(len(done), np.int64)
    if done.any():
        final = info["final_info"]
        values[done] = np.array(final[key])[done]
    return values


def make_envs(cfg: TrainConfig, grid: GridMap) -> gym.vector.SyncVectorEnv:
    rules = GridRules(exclude_last=cfg.exclude_last, max_steps=cfg.max_episode_steps)
    fns = [lambda: LoopClosureGrid(grid, rules) for _ in range(cfg.n_envs)]
    return gym.vector.SyncVectorEnv(fns, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
