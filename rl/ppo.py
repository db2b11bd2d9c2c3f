"""PPO for the loop-closure grid world (dissertation Sec. 3.4.5, 3.6, Algorithm 3; SPEC 6.9).

Synchronous actors (a gymnasium vector environment, rl/rollout.py) collect trajectories with separate actor
and critic networks (3 conv + LSTM cell each, rl/networks.py); advantages are GAE (lambda = 1 gives eq.
3.18's reward-to-go minus the critic's value); the clipped objective (eqs. 3.16-3.17) is maximised with Adam.

Each update learns from the entropy-chosen batch length (eq. 3.20) with the balanced policy loss
(rl/batching.py), plus the auxiliary visit-memory loss of the actor (rl/auxiliary.py). Runs checkpoint and
resume, and can start from another run's networks (rl/checkpoint.py). The hyper-parameters are
``TrainConfig`` (rl/train_config.py).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import nn

from rl import auxiliary
from rl.auxiliary import AUX_TARGETS, aux_action_outputs, aux_classifier_targets
from rl.batching import balance_weights, batch_length
from rl.checkpoint import init_from_checkpoint, resume_trainer, save_checkpoint
from rl.gridmap import GridMap
from rl.networks import RecurrentNet, input_pool
from rl.rollout import Buffer, distinct_frames, make_envs, step_info
from rl.train_config import TrainConfig, TrainResult

# also importable from here, as before the trainer's helpers had modules of their own
__all__ = [
    "AUX_TARGETS",
    "Buffer",
    "TrainConfig",
    "TrainResult",
    "Trainer",
    "aux_action_outputs",
    "aux_classifier_targets",
    "balance_weights",
    "batch_length",
    "distinct_frames",
    "make_envs",
    "step_info",
]


class Trainer:
    """Collects batches with the current policy and improves it by PPO; checkpoints and resumes."""

    def __init__(self, cfg: TrainConfig, grid: GridMap | None = None):
        if cfg.n_envs % cfg.minibatches:
            raise ValueError("n_envs must be a multiple of minibatches")
        if cfg.batch not in ("entropy", "fixed"):
            raise ValueError(f"unknown batch mode {cfg.batch!r}")
        if cfg.aux_targets not in AUX_TARGETS:
            raise ValueError(f"unknown aux_targets {cfg.aux_targets!r} (one of {', '.join(AUX_TARGETS)})")
        torch.set_num_threads(cfg.threads)
        torch.manual_seed(cfg.seed)
        self.cfg = cfg
        self.grid = grid or GridMap.load(cfg.map)
        self.envs = make_envs(cfg, self.grid)
        self.n_actions = self.grid.n_loops + 1
        pool = cfg.pool or input_pool(self.grid.shape)
        self.actor = RecurrentNet(
            self.n_actions,
            cfg.hidden,
            pool=pool,
            aux=auxiliary.aux_outputs(cfg.aux_targets, self.grid.n_loops) if cfg.aux_coef > 0 else 0,
        )
        self.critic = RecurrentNet(1, cfg.hidden, head_gain=1.0, pool=pool)
        with torch.no_grad():  # prior: "no loop closure" is the common case (probability no_lc_prior at start)
            self.actor.head.bias[0] = np.log(cfg.no_lc_prior) - np.log((1 - cfg.no_lc_prior) / self.grid.n_loops)
        if cfg.init_from:
            init_from_checkpoint(Path(cfg.init_from), {"actor": self.actor, "critic": self.critic})
        self.optimizer = torch.optim.Adam([*self.actor.parameters(), *self.critic.parameters()], lr=cfg.lr, eps=1e-5)
        self.buffer = Buffer.empty(cfg.rollout, cfg.n_envs, cfg.hidden, self.grid.n_loops)
        self.global_step = 0
        self.curve: list[dict] = []
        # carried in checkpoints: the memory pretraining's record and the wall time of earlier segments
        self.history: dict = {"pretrain": None, "wall_s": 0.0}
        obs, _ = self.envs.reset(seed=cfg.seed)
        self.next_obs, self.next_start = obs, np.ones(cfg.n_envs, bool)
        self.state = [
            t.numpy() for t in (*self.actor.initial_state(cfg.n_envs), *self.critic.initial_state(cfg.n_envs))
        ]
        self._returns = np.zeros(cfg.n_envs)
        self._finished: list[float] = []

    # ------------------------------------------------------------ collection

    @torch.no_grad()
    def collect(self) -> None:
        """Fill the buffer up to its length with the current policy."""
        b, n = self.buffer, self.cfg.n_envs
        while b.filled < len(b.obs):
            t = b.filled
            ah, ac, ch, cc = (torch.from_numpy(s) for s in self.state)
            keep = torch.from_numpy(~self.next_start).float().unsqueeze(-1)
            ah, ac, ch, cc = ah * keep, ac * keep, ch * keep, cc * keep
            b.obs[t], b.starts[t] = self.next_obs, self.next_start
            b.states[t] = np.stack([s.numpy() for s in (ah, ac, ch, cc)])
            obs_t = torch.from_numpy(self.next_obs)
            logits, ah, ac = self.actor.step(obs_t, ah, ac)
            _, ch, cc = self.critic.step(obs_t, ch, cc)
            dist = torch.distributions.Categorical(logits=logits)
            action = dist.sample()
            b.actions[t], b.logprobs[t] = action.numpy(), dist.log_prob(action).numpy()
            obs, reward, term, trunc, info = self.envs.step(action.numpy())
            done = term | trunc
            b.rewards[t], b.dones[t], b.targets[t] = reward, done, step_info(info, "correct_action", done)
            b.loop[t] = step_info(info, "loop", done)
            b.at_loop[t] = b.loop[t] >= 0
            b.visited[t] = step_info(info, "visited", done)
            self.state = [s.numpy() for s in (ah, ac, ch, cc)]
            self.next_obs, self.next_start = obs, term | trunc
            self._returns += reward
            for k in np.flatnonzero(term | trunc):
                self._finished.append(float(self._returns[k]))
                self._returns[k] = 0.0
            b.filled += 1
            self.global_step += n

    def aux_loss(
        self,
        aux_logits: torch.Tensor,
        bits: torch.Tensor,
        place: torch.Tensor,
        action: torch.Tensor,
        place_w: torch.Tensor,
        action_w: torch.Tensor,
    ) -> torch.Tensor:
        """The auxiliary loss over (T, B) steps (``auxiliary.aux_loss`` for this run's targets and map)."""
        return auxiliary.aux_loss(
            self.cfg.aux_targets, self.grid.n_loops, aux_logits, bits, place, action, place_w, action_w
        )

    def aux_target_bits(self, T: int) -> np.ndarray:
        """(T, n_envs, aux outputs) targets of the auxiliary head for the first T buffered steps."""
        return self.aux_targets_of(self.buffer.visited[:T], self.buffer.loop[:T])

    def aux_targets_of(self, visited: np.ndarray, loop: np.ndarray) -> np.ndarray:
        """Binary targets of the auxiliary head from per-step visit bits (..., L) and location stood on (...)."""
        return auxiliary.aux_bits(self.cfg.aux_targets, self.grid.n_loops, visited, loop)

    # ------------------------------------------------------------ update

    def update(self) -> dict:
        """One PPO update on the chosen batch length; returns the update's statistics."""
        cfg, b = self.cfg, self.buffer
        T = batch_length(b.targets, self.n_actions, cfg.b1, cfg.b2) if cfg.batch == "entropy" else cfg.n_steps
        frames, index = distinct_frames(b.obs[: b.filled])
        starts = torch.from_numpy(b.starts[: b.filled])
        s0 = torch.from_numpy(b.states[0])
        with torch.no_grad():  # values of every buffered step (and the next observation) with the current critic
            values = self.critic.sequence(frames, index, starts, s0[2], s0[3]).squeeze(-1).numpy()
            if b.filled == T:
                ch, cc = (torch.from_numpy(s) for s in self.state[2:])
                keep = torch.from_numpy(~self.next_start).float().unsqueeze(-1)
                nxt, _, _ = self.critic.step(torch.from_numpy(self.next_obs), ch * keep, cc * keep)
                bootstrap = nxt.squeeze(-1).numpy()
            else:
                bootstrap = values[T]
        advantages = self._gae(b.rewards[:T] * cfg.reward_scale, b.dones[:T], values[:T], bootstrap)
        returns = advantages + values[:T]
        stats = self._optimise(T, frames, index[:T], starts[:T], s0, advantages, returns)
        targets, actions = b.targets[:T], b.actions[:T]
        stats.update(
            batch_length=T,
            lc_due=int((targets > 0).sum()),
            lc_taken=int((actions > 0).sum()),
            lc_correct=int(((actions == targets) & (targets > 0)).sum()),
        )
        b.drop_front(T)
        return stats

    def balance_power(self) -> float:
        """1 = fully balanced weights, 0 = plain PPO; decreases linearly to 0 at ``balance`` of training."""
        if self.cfg.balance <= 0:
            return 0.0
        return max(0.0, 1.0 - self.global_step / (self.cfg.balance * self.cfg.total_steps))

    def ent_coef(self) -> float:
        frac = min(1.0, self.global_step / self.cfg.total_steps)
        return self.cfg.ent_coef + frac * (self.cfg.ent_coef_final - self.cfg.ent_coef)

    def _gae(self, rewards, dones, values, bootstrap) -> np.ndarray:
        cfg = self.cfg
        adv = np.zeros_like(rewards)
        last = np.zeros(rewards.shape[1], np.float32)
        for t in reversed(range(len(rewards))):
            next_value = bootstrap if t == len(rewards) - 1 else values[t + 1]
            alive = 1.0 - dones[t]
            delta = rewards[t] + cfg.gamma * next_value * alive - values[t]
            last = delta + cfg.gamma * cfg.gae_lambda * alive * last
            adv[t] = last
        return adv

    def _optimise(self, T, frames, index, starts, s0, advantages, returns) -> dict:
        cfg, b = self.cfg, self.buffer
        actions = torch.from_numpy(b.actions[:T])
        actions_target = torch.from_numpy(b.targets[:T])
        old_logp = torch.from_numpy(b.logprobs[:T])
        adv_t, ret_t = torch.from_numpy(advantages), torch.from_numpy(returns)
        visited = torch.from_numpy(self.aux_target_bits(T))
        place, place_w, action_w = aux_classifier_targets(b.loop[:T], b.targets[:T])
        kinds = b.at_loop[:T] if cfg.balance_first_visits else None
        weight = torch.from_numpy(balance_weights(b.targets[:T], kinds) ** self.balance_power())
        groups = np.array_split(np.arange(cfg.n_envs), cfg.minibatches)
        rng = np.random.default_rng(cfg.seed + self.global_step)
        clipped, aux_losses = [], []
        for _ in range(cfg.epochs):
            for g in rng.permutation(len(groups)):
                e = torch.from_numpy(groups[g])
                used, sub = torch.unique(index[:, e], return_inverse=True)
                f = frames[used]
                if cfg.aux_coef > 0:
                    logits, aux_logits = self.actor.sequence(f, sub, starts[:, e], s0[0][e], s0[1][e], with_aux=True)
                    aux_loss = self.aux_loss(
                        aux_logits, visited[:, e], place[:, e], actions_target[:, e], place_w[:, e], action_w[:, e]
                    )
                else:
                    logits = self.actor.sequence(f, sub, starts[:, e], s0[0][e], s0[1][e])
                    aux_loss = torch.zeros(())
                value = self.critic.sequence(f, sub, starts[:, e], s0[2][e], s0[3][e]).squeeze(-1)
                dist = torch.distributions.Categorical(logits=logits)
                logp = dist.log_prob(actions[:, e])
                ratio = torch.exp(logp - old_logp[:, e])
                adv = adv_t[:, e]
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
                surrogate = torch.min(ratio * adv, torch.clamp(ratio, 1 - cfg.clip, 1 + cfg.clip) * adv)
                policy_loss = -(weight[:, e] * surrogate).mean()
                value_loss = 0.5 * ((value - ret_t[:, e]) ** 2).mean()
                entropy = dist.entropy().mean()
                loss = policy_loss + cfg.vf_coef * value_loss - self.ent_coef() * entropy + cfg.aux_coef * aux_loss
                self.optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(self.actor.parameters(), cfg.max_grad_norm)
                nn.utils.clip_grad_norm_(self.critic.parameters(), cfg.max_grad_norm)
                self.optimizer.step()
                clipped.append(float(((ratio - 1).abs() > cfg.clip).float().mean()))
                aux_losses.append(aux_loss.item())
        return {
            "policy_loss": policy_loss.item(),
            "value_loss": value_loss.item(),
            "entropy": entropy.item(),
            "clip_fraction": float(np.mean(clipped)),
            "aux_loss": float(np.mean(aux_losses)),
        }

    # ------------------------------------------------------------ loop, checkpoints

    def train(self, checkpoint: Path | None = None, progress: Callable[[int, dict], None] | None = None) -> TrainResult:
        start = time.perf_counter()
        updates = 0
        while self.global_step < self.cfg.total_steps:
            self.collect()
            stats = self.update()
            episodes, self._finished = self._finished, []
            stats.update(
                step=self.global_step,
                episodes=len(episodes),
                mean_return=float(np.mean(episodes)) if episodes else None,
            )
            self.curve.append(stats)
            updates += 1
            if progress:
                progress(self.global_step, stats)
            if checkpoint and updates % self.cfg.checkpoint_every == 0:
                self.save(checkpoint)
        if checkpoint:
            self.save(checkpoint)
        return TrainResult(self.cfg, self.curve, time.perf_counter() - start)

    def save(self, path: Path) -> None:
        """Networks, optimiser, step count and reward curve; written to a temporary file, then renamed."""
        save_checkpoint(self, path)

    @classmethod
    def resume(cls, path: Path, total_steps: int | None = None) -> Trainer:
        """Continue a saved run (the environments restart; networks, optimiser and counters carry on)."""
        return resume_trainer(cls, path, total_steps)
