"""Hyper-parameters of a PPO training run of the loop-closure policy, and what a run returns (rl/ppo.py)."""

from __future__ import annotations

from dataclasses import dataclass, field


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
    aux_coef: float = 0.3  # auxiliary visit-memory loss of the actor (rl/auxiliary.py); 0 = off, no aux head
    aux_targets: str = "visited"  # "visited" (n_loops bits) or "visited+here+due" (3 x n_loops bits; auxiliary.py)
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


@dataclass
class TrainResult:
    config: TrainConfig
    curve: list[dict] = field(default_factory=list)  # per update: step, mean episode return, batch length...
    wall_s: float = 0.0
