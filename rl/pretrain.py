"""Supervised pretraining of the actor's visit memory on random walks (our decision, beyond the dissertation).

Whether a loop closure is due is a matter of memory: the location stood on must have been first visited
more than ``c`` steps ago. Neither PPO's sparse reward nor the auxiliary loss during PPO taught the LSTM
that memory (docs/rl.md: the trained policies act on first visits about as often as on revisits, or miss
revisits as often). The agent's motion does not depend on the policy, so random walks recorded with any
action are exactly the walks the policy will see. Here the actor's encoder, LSTM and auxiliary head learn
the auxiliary targets (``Trainer.aux_loss``: visit bits, location, correct action) by supervised learning
on such walks, with backpropagation through each whole walk, plus an extra loss on the one bit that
decides a loop closure (the visit bit of the location stood on). The LSTM's forget gates start open
(``forget_bias``), so memory persists from the start. The critic's encoder and LSTM start as copies.
PPO then trains the policy head on top (and keeps the auxiliary loss). With ``policy_from_aux`` the policy
head starts as a copy of the auxiliary head's correct-action classifier (an imitation start: the
classifier is trained on the environment's correct actions), and PPO fine-tunes it on the reward.

The measure of the memory (``memory_scores``), on held-out walks, on the steps where the agent stands on
a loop-closure location: the fraction of due visits whose visit bit is set, and of first visits (or
revisits within ``c`` steps) whose bit is clear; and the precision and recall of the correct-action
classifier's greedy choice, counted as ``eval-lc`` counts a policy's.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from rl.auxiliary import aux_action_outputs, aux_classifier_targets
from rl.env import GridRules, LoopClosureGrid
from rl.gridmap import GridMap
from rl.ppo import Trainer
from rl.rollout import distinct_frames


@dataclass
class PretrainConfig:
    epochs: int = 0  # passes over the recorded walks; 0 = no pretraining
    walks: int = 512  # random walks recorded for training
    length: int = 128  # steps per walk (backpropagation runs through the whole walk)
    held_out: int = 16  # further walks for ``memory_scores``
    batch: int = 16  # walks per gradient step
    lr: float = 1e-3
    forget_bias: float = 3.0  # initial forget-gate bias of the actor's LSTM (sigmoid(3) = 0.95 kept per step)
    location_weight: float = 3.0  # weight of the extra loss on the visit bit of the location stood on
    seed: int = 0
    policy_from_aux: bool = False  # start the policy head as a copy of the aux correct-action classifier


@dataclass
class Walks:
    """Random walks: per step (T, N, ...) the observation before the step and what the environment reported."""

    obs: np.ndarray  # (T, N, 84, 84, 3) uint8
    visited: np.ndarray  # (T, N, L) bool: env info "visited"
    loop: np.ndarray  # (T, N): the location stood on, -1 for none
    action: np.ndarray  # (T, N): the correct action (0, or l + 1 when a loop closure at l is due)

    def take(self, columns: np.ndarray) -> Walks:
        return Walks(*(a[:, columns] for a in (self.obs, self.visited, self.loop, self.action)))


def record_walks(grid: GridMap, n: int, length: int, seed: int, exclude_last: int = 4) -> Walks:
    """``n`` walks of ``length`` steps from random starts (seeds ``seed``, ``seed + 1``, ...)."""
    env = LoopClosureGrid(grid, GridRules(exclude_last=exclude_last, terminate=False, max_steps=0))
    walks = Walks(
        np.zeros((length, n, *env.observation_space.shape), np.uint8),
        np.zeros((length, n, grid.n_loops), bool),
        np.full((length, n), -1, np.int64),
        np.zeros((length, n), np.int64),
    )
    for j in range(n):
        obs, _ = env.reset(seed=seed + j)
        for t in range(length):
            walks.obs[t, j] = obs
            obs, _, _, _, info = env.step(0)
            walks.visited[t, j], walks.loop[t, j], walks.action[t, j] = (
                info["visited"],
                info["loop"],
                info["correct_action"],
            )
    return walks


def location_bits(aux_logits: torch.Tensor, loop: np.ndarray, n_loops: int) -> torch.Tensor:
    """(T, N) logit of the visit bit of the location stood on (meaningless where ``loop`` is -1)."""
    index = torch.from_numpy(np.maximum(loop, 0))[..., None]
    return aux_logits[..., :n_loops].gather(-1, index)[..., 0]


def action_logits(aux_logits: torch.Tensor, n_loops: int) -> torch.Tensor:
    """The correct-action classifier's logits: the last ``n_loops + 1`` aux outputs ("visited+place+action")."""
    return aux_logits[..., aux_action_outputs(n_loops)]


def memory_scores(aux_logits: torch.Tensor, walks: Walks, n_loops: int) -> dict:
    """On the steps at a loop-closure location: share of due visits with the bit set, of the others with it clear.
    Over all steps: precision and recall of the action classifier's greedy loop-closure actions."""
    on = walks.loop >= 0
    due = walks.action > 0
    bit = (location_bits(aux_logits, walks.loop, n_loops) > 0).numpy()
    chosen = action_logits(aux_logits, n_loops).argmax(-1).numpy()
    correct = int(((chosen == walks.action) & due).sum())
    return {
        "due_recalled": float(bit[on & due].mean()) if (on & due).any() else float("nan"),
        "first_visits_recognised": float((~bit[on & ~due]).mean()) if (on & ~due).any() else float("nan"),
        "due_visits": int((on & due).sum()),
        "other_visits": int((on & ~due).sum()),
        "action_precision": correct / max(int((chosen > 0).sum()), 1),
        "action_recall": correct / max(int(due.sum()), 1),
    }


class MemoryPretrainer:
    """Trains a ``Trainer``'s actor (encoder, LSTM, auxiliary head) on recorded walks; see the module doc."""

    def __init__(self, trainer: Trainer, cfg: PretrainConfig):
        aux_head = trainer.actor.aux_head
        if aux_head is None:
            raise ValueError("memory pretraining needs the actor's auxiliary head (aux_coef > 0)")
        if trainer.cfg.aux_targets != "visited+place+action":
            raise ValueError("memory pretraining needs the aux targets visited+place+action (their action classifier)")
        self.trainer, self.cfg = trainer, cfg
        self.n_loops = trainer.grid.n_loops
        actor = trainer.actor
        with torch.no_grad():
            h = actor.hidden
            # PyTorch gate order: input, forget, cell, output
            actor.lstm.get_parameter("bias_ih_l0")[h : 2 * h] = cfg.forget_bias
            actor.lstm.get_parameter("bias_hh_l0")[h : 2 * h] = 0.0
        self.aux_head = aux_head
        self.params = [*actor.encoder.parameters(), *actor.lstm.parameters(), *aux_head.parameters()]
        self.optimizer = torch.optim.Adam(self.params, lr=cfg.lr)

    def loss(self, walks: Walks) -> tuple[torch.Tensor, torch.Tensor]:
        """The auxiliary loss over whole walks, plus the weighted loss of the decisive bit; and the aux logits."""
        actor, T, N = self.trainer.actor, *walks.loop.shape
        frames, index = distinct_frames(walks.obs)
        starts = torch.zeros(T, N, dtype=torch.bool)
        starts[0] = True
        h, c = actor.initial_state(N)
        _, aux = actor.sequence(frames, index, starts, h, c, with_aux=True)
        place, place_w, action_w = aux_classifier_targets(walks.loop, walks.action)
        loss = self.trainer.aux_loss(
            aux,
            torch.from_numpy(self.trainer.aux_targets_of(walks.visited, walks.loop)),
            place,
            torch.from_numpy(walks.action),
            place_w,
            action_w,
        )
        on = torch.from_numpy(walks.loop >= 0)
        if on.any() and self.cfg.location_weight > 0:
            bits = location_bits(aux, walks.loop, self.n_loops)
            due = torch.from_numpy(walks.action > 0).float()
            loss = loss + self.cfg.location_weight * nn.functional.binary_cross_entropy_with_logits(bits[on], due[on])
        return loss, aux

    def run(self, progress: Callable[[int, dict], None] | None = None) -> list[dict]:
        """Record the walks, train for ``epochs``, copy the encoder and LSTM to the critic (and the action
        classifier to the policy head, with ``policy_from_aux``); per-epoch statistics."""
        cfg, grid = self.cfg, self.trainer.grid
        exclude = self.trainer.cfg.exclude_last
        start = time.perf_counter()
        train = record_walks(grid, cfg.walks, cfg.length, cfg.seed, exclude)
        test = record_walks(grid, cfg.held_out, cfg.length, cfg.seed + 1_000_000, exclude)
        rng = np.random.default_rng(cfg.seed)
        history = []
        for epoch in range(cfg.epochs):
            losses = []
            for columns in np.array_split(rng.permutation(cfg.walks), max(1, cfg.walks // cfg.batch)):
                loss, _ = self.loss(train.take(columns))
                self.optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(self.params, 1.0)
                self.optimizer.step()
                losses.append(loss.item())
            with torch.no_grad():
                _, aux = self.loss(test)
            row = {
                "epoch": epoch + 1,
                "loss": float(np.mean(losses)),
                **memory_scores(aux, test, self.n_loops),
                "wall_s": round(time.perf_counter() - start, 1),
            }
            history.append(row)
            if progress:
                progress(epoch + 1, row)
        actor, critic = self.trainer.actor, self.trainer.critic
        critic.encoder.load_state_dict(actor.encoder.state_dict())
        critic.lstm.load_state_dict(actor.lstm.state_dict())
        if cfg.policy_from_aux:
            with torch.no_grad():
                rows = aux_action_outputs(self.n_loops)
                actor.head.weight.copy_(self.aux_head.weight[rows])
                actor.head.bias.copy_(self.aux_head.bias[rows])
        return history
