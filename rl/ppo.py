"""PPO for the loop-closure grid world (dissertation Sec. 3.4.5, 3.6, Algorithm 3; SPEC 6.9).

Synchronous actors (a gymnasium vector environment) collect trajectories with separate actor and
critic networks (3 conv + LSTM cell each); advantages are GAE (lambda = 1 gives eq. 3.18's reward-to-go
minus the critic's value); the clipped objective (eqs. 3.16-3.17) is maximised with Adam.

Entropy-based variable batch size (eq. 3.20). Loop closures are rare in a random walk, so a fixed
batch may hold none and the policy then only learns "no loop closure" (Fig. 3.10a-b). Precisely:
the actors run in lockstep and keep a buffer of up to ``b2`` steps each; for every length
n in [b1, b2] let p_n be the empirical distribution, over the n * n_envs steps of the candidate batch,
of the correct actions (0 or the due location, which the environment reports); the batch length is
n* = argmax_n H(p_n) (the smallest n on ties), i.e. the prefix richest in loop-closure steps. The
update uses the first n* steps of every actor; the remaining b2 - n* steps, collected by the same
policy, stay in the buffer as the start of the next batch (their stored log-probabilities keep the
PPO ratio correct), so no experience is thrown away. ``batch="fixed"`` uses n* = ``n_steps``.

Balanced policy loss. Even the best prefix holds few due loop closures (2-14 % of steps), and the
"no loop closure" steps then drive the actor to never close a loop before it has learned to tell the
places apart (the collapse of Fig. 3.10a). With ``balance`` the clipped surrogate of each step is
weighted so that due and not-due steps carry equal total weight: the batch is re-weighted towards
maximum correct-action entropy, the limit eq. 3.20 moves towards. ``balance_first_visits`` makes it three
kinds (due; on a loop-closure location where none is due, i.e. a first visit, the case only memory can
tell; any other step): it pushes the LSTM to remember visits, but the policy then learns to close loops
at all much later (config2: P 7 % / R 7 % after 70k steps, against R near 100 % by 40k without it). Weighting states does not change which
action is best in a state the policy can tell apart, only how fast each is learned; where its memory
cannot tell a due visit from a first one it would favour loop closures, so the weights are annealed
to 1 (plain PPO) by ``balance`` x total_steps.

Auxiliary visit-memory loss (``aux_coef``; UNREAL-style auxiliary task with privileged simulator
information). Whether a loop closure is due depends on memory: the current location must have been first
visited more than c steps ago. From the sparse PPO reward alone the LSTM did not learn it, and the
policies also closed "loops" on first visits. The environment reports that memory in ``info["visited"]``
(one bit per location); the actor has a second linear head on its LSTM output (``aux_head``, n_loops
logits) trained at every step with binary cross-entropy against it, weighted by ``aux_coef`` and added
to the PPO loss. The gradient reaches the encoder and LSTM, not the policy head, which the PPO objective
alone trains; the critic is unchanged. Acting, the ONNX export and evaluation never use the aux head.
``aux_targets="visited+here+due"`` adds, per location, "the agent stands on it" and "a loop closure is due
there" (= here and visited) to the aux head's targets: the recognition of the location and the conjunction
a linear policy head needs, as features of the LSTM output (on maps with many locations the visit memory
alone was not learned). The policy head is still trained by the PPO objective only.

``init_from`` copies the parameters of another checkpoint whose shapes match (encoder, LSTM; heads only
when the number of locations is the same): a curriculum from a smaller map.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from rl.env import GridRules, LoopClosureGrid
from rl.gridmap import GridMap
from rl.networks import RecurrentNet, input_pool

log = logging.getLogger(__name__)


@dataclass
class TrainConfig:
    """Hyper-parameters of a training run (defaults: the values used for docs/benchmarks.md)."""

    map: str = "config1"  # shipped configuration name or map file
    total_steps: int = 300_000  # environment steps over all actors
    n_envs: int = 8  # synchronous actors
    batch: str = "entropy"  # "entropy" (eq. 3.20) or "fixed"
    n_steps: int = 128  # fixed batch: steps per actor per update
    b1: int = 64  # entropy batch: shortest trajectory per actor
    b2: int = 256  # entropy batch: longest trajectory per actor
    lr: float = 3e-4  # Adam learning rate
    gamma: float = 0.9  # discount (the action does not move the agent, so short horizons suffice)
    gae_lambda: float = 0.95
    epochs: int = 4  # optimisation passes over each batch
    minibatches: int = 4  # actors are split into this many groups per pass
    clip: float = 0.2  # PPO ratio clip (eq. 3.17)
    balance: float = 0.75  # balanced policy loss, annealed to none at this fraction of training; 0 = off
    balance_first_visits: bool = False  # also balance first visits at loop-closure locations (slower; see doc)
    no_lc_prior: float = 0.8  # initial probability of action 0, so early episodes last long enough to see loops
    ent_coef: float = 0.2  # entropy bonus at the start: keeps the rare loop-closure actions explored
    ent_coef_final: float = 0.005  # ... annealed linearly to this over total_steps
    vf_coef: float = 0.5  # critic loss weight
    aux_coef: float = 0.3  # auxiliary visit-memory loss of the actor (see module doc); 0 = off, no aux head
    aux_targets: str = "visited"  # "visited" (n_loops bits) or "visited+here+due" (3 x n_loops bits; see module doc)
    init_from: str = ""  # checkpoint whose parameters of matching shape initialise the networks (curriculum)
    max_grad_norm: float = 0.5  # per network
    reward_scale: float = 0.01  # rewards (+-100, +10, -500) are scaled for learning; curves report them unscaled
    hidden: int = 128  # LSTM cell size
    pool: int = 0  # input average pooling 1, 2 or 4; 0 chooses from the grid size
    seed: int = 0
    exclude_last: int = 4  # c of the due-loop-closure rule
    max_episode_steps: int = 512  # training episodes are truncated here
    threads: int = 2  # torch intra-op threads
    checkpoint_every: int = 20  # updates between checkpoints

    @property
    def rollout(self) -> int:
        return self.b2 if self.batch == "entropy" else self.n_steps


# aux_targets -> aux logits: (per location, extra); "visited+place+action" adds two (n_loops + 1)-way classifiers
AUX_TARGETS = {"visited": (1, 0), "visited+here+due": (3, 0), "visited+place+action": (3, 2)}


def aux_action_outputs(n_loops: int) -> slice:
    """Where the correct-action classifier's L + 1 logits sit among the aux head's "visited+place+action"
    outputs: after the L visit bits and the L + 1 place logits."""
    return slice(2 * n_loops + 1, 3 * n_loops + 2)


def batch_length(targets: np.ndarray, n_actions: int, b1: int, b2: int) -> int:
    """Eq. 3.20: the n in [b1, b2] maximising the entropy of the correct actions of steps [0, n).

    ``targets`` is (T >= b2, n_envs) of correct actions.
    """
    onehot = np.zeros((b2, n_actions))
    np.add.at(onehot, (np.repeat(np.arange(b2), targets.shape[1]), targets[:b2].ravel()), 1.0)
    counts = np.cumsum(onehot, axis=0)[b1 - 1 :]  # counts[i] covers steps [0, b1 + i)
    p = counts / counts.sum(axis=1, keepdims=True)
    entropy = -(np.where(p > 0, p * np.log(np.maximum(p, 1e-12)), 0.0)).sum(axis=1)
    return int(b1 + np.argmax(entropy))


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


@dataclass
class TrainResult:
    config: TrainConfig
    curve: list[dict] = field(default_factory=list)  # per update: step, mean episode return, batch length...
    wall_s: float = 0.0


def balance_weights(targets: np.ndarray, at_loop: np.ndarray | None = None) -> np.ndarray:
    """Per-step weights (mean 1) giving each kind of step equal total weight: a loop closure is due; the agent
    is on a loop-closure location where none is due (a first visit: what memory must learn), when
    ``at_loop`` is given; any other step."""
    kind = np.where(targets > 0, 2, np.where(at_loop, 1, 0) if at_loop is not None else 0)
    counts = np.bincount(kind.ravel(), minlength=3)
    present = counts > 0
    per_kind = np.where(present, kind.size / (present.sum() * np.maximum(counts, 1)), 0.0)
    return per_kind[kind].astype(np.float32)


def aux_classifier_targets(loop: np.ndarray, action: np.ndarray) -> tuple[torch.Tensor, ...]:
    """Targets and per-step weights of the aux head's two classifiers ("visited+place+action"), from the
    location stood on (-1 for none) and the correct action: place (0 = none, l + 1 = location l) weighted
    so being on a location carries the weight of the rest; the action weighted in three kinds (due; on a
    location where none is due, i.e. a first visit, which only memory tells apart; elsewhere)."""
    place = loop + 1
    return (
        torch.from_numpy(place),
        torch.from_numpy(balance_weights(place)),
        torch.from_numpy(balance_weights(action, loop >= 0)),
    )


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
            self.n_actions, cfg.hidden, pool=pool, aux=self._aux_outputs() if cfg.aux_coef > 0 else 0
        )
        self.critic = RecurrentNet(1, cfg.hidden, head_gain=1.0, pool=pool)
        with torch.no_grad():  # prior: "no loop closure" is the common case (probability no_lc_prior at start)
            self.actor.head.bias[0] = np.log(cfg.no_lc_prior) - np.log((1 - cfg.no_lc_prior) / self.grid.n_loops)
        if cfg.init_from:
            self._init_from(Path(cfg.init_from))
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

    def _init_from(self, path: Path) -> None:
        """Curriculum: copy the parameters of a checkpoint whose shapes match; the rest keep their initialisation."""
        ckpt = torch.load(path, weights_only=False)
        copied = []
        for name, net in (("actor", self.actor), ("critic", self.critic)):
            own = net.state_dict()
            same = {k: v for k, v in ckpt[name].items() if k in own and own[k].shape == v.shape}
            own.update(same)
            net.load_state_dict(own)
            copied += [f"{name}.{k}" for k in same]
        if not copied:
            raise ValueError(f"{path}: no parameter of matching shape to initialise from")
        log.info("initialised %d tensors from %s", len(copied), path)

    def _aux_outputs(self) -> int:
        per_location, extra = AUX_TARGETS[self.cfg.aux_targets]
        return self.grid.n_loops * per_location + extra

    def aux_loss(
        self,
        aux_logits: torch.Tensor,
        bits: torch.Tensor,
        place: torch.Tensor,
        action: torch.Tensor,
        place_w: torch.Tensor,
        action_w: torch.Tensor,
    ) -> torch.Tensor:
        """The auxiliary loss over (T, B) steps. "visited+place+action": BCE of the visit memory plus two
        classifiers (location stood on or none; the correct action), each step weighted so that the rare
        classes carry the same total weight as the rest: on a location, for the location classifier; a loop
        closure due and, apart, standing on a location where none is due (a first visit, which only memory
        tells from a due one), for the action classifier."""
        L = self.grid.n_loops
        if self.cfg.aux_targets != "visited+place+action":
            return nn.functional.binary_cross_entropy_with_logits(aux_logits, bits)
        bce = nn.functional.binary_cross_entropy_with_logits(aux_logits[..., :L], bits)
        ce = nn.functional.cross_entropy
        place_loss = ce(aux_logits[..., L : 2 * L + 1].reshape(-1, L + 1), place.reshape(-1), reduction="none")
        action_loss = ce(
            aux_logits[..., aux_action_outputs(L)].reshape(-1, L + 1), action.reshape(-1), reduction="none"
        )
        return bce + (place_w.reshape(-1) * place_loss).mean() + (action_w.reshape(-1) * action_loss).mean()

    def aux_target_bits(self, T: int) -> np.ndarray:
        """(T, n_envs, aux outputs) targets of the auxiliary head for the first T buffered steps."""
        return self.aux_targets_of(self.buffer.visited[:T], self.buffer.loop[:T])

    def aux_targets_of(self, visited: np.ndarray, loop: np.ndarray) -> np.ndarray:
        """Binary targets of the auxiliary head from per-step visit bits (..., L) and location stood on (...)."""
        if self.cfg.aux_targets != "visited+here+due":
            return visited.astype(np.float32)
        here = loop[..., None] == np.arange(self.grid.n_loops)
        return np.concatenate([visited, here, here & visited], axis=-1).astype(np.float32)

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
        tmp = Path(path).with_suffix(".tmp")
        torch.save(
            {
                "config": asdict(self.cfg),
                "grid": self.grid.to_json(),
                "actor": self.actor.state_dict(),
                "critic": self.critic.state_dict(),
                "optimizer": self.optimizer.state_dict(),
                "global_step": self.global_step,
                "curve": self.curve,
                "history": self.history,
            },
            tmp,
        )
        tmp.replace(path)

    @classmethod
    def resume(cls, path: Path, total_steps: int | None = None) -> Trainer:
        """Continue a saved run (the environments restart; networks, optimiser and counters carry on)."""
        ckpt = torch.load(path, weights_only=False)
        # runs saved before the auxiliary loss existed have no aux head: they continue without it
        cfg = TrainConfig(**{"aux_coef": 0.0, **ckpt["config"]})
        if total_steps is not None:
            cfg.total_steps = total_steps
        init_from, cfg.init_from = cfg.init_from, ""  # the saved networks replace any initialisation
        trainer = cls(cfg, GridMap.from_json(ckpt["grid"]))
        trainer.cfg.init_from = init_from
        try:
            trainer.actor.load_state_dict(ckpt["actor"])
        except RuntimeError as exc:
            raise ValueError(
                f"{path}: the checkpoint's actor does not match its configuration "
                f"(aux_coef {cfg.aux_coef}): {str(exc).splitlines()[0]}"
            ) from exc
        trainer.critic.load_state_dict(ckpt["critic"])
        trainer.optimizer.load_state_dict(ckpt["optimizer"])
        trainer.global_step, trainer.curve = ckpt["global_step"], ckpt["curve"]
        trainer.history = {**trainer.history, **ckpt.get("history", {})}
        return trainer


def curve_json(result: TrainResult) -> str:
    return json.dumps({"config": asdict(result.config), "wall_s": result.wall_s, "curve": result.curve})
