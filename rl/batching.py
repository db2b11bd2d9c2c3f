"""Which steps a PPO update of the loop-closure policy learns from, and how much each weighs (rl/ppo.py).

Entropy-based variable batch size (dissertation eq. 3.20). Loop closures are rare in a random walk, so a
fixed batch may hold none and the policy then only learns "no loop closure" (Fig. 3.10a-b). Precisely:
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
maximum correct-action entropy, the limit eq. 3.20 moves towards. ``balance_first_visits`` makes it
three kinds (due; on a loop-closure location where none is due, i.e. a first visit, the case only
memory can tell; any other step): it pushes the LSTM to remember visits, but the policy then learns to
close loops at all much later (config2: P 7 % / R 7 % after 70k steps, against R near 100 % by 40k
without it). Weighting states does not change which action is best in a state the policy can tell
apart, only how fast each is learned; where its memory cannot tell a due visit from a first one it
would favour loop closures, so the weights are annealed to 1 (plain PPO) by ``balance`` x total_steps.
"""

from __future__ import annotations

import numpy as np


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


def balance_weights(targets: np.ndarray, at_loop: np.ndarray | None = None) -> np.ndarray:
    """Per-step weights (mean 1) giving each kind of step equal total weight: a loop closure is due; the agent
    is on a loop-closure location where none is due (a first visit: what memory must learn), when
    ``at_loop`` is given; any other step."""
    kind = np.where(targets > 0, 2, np.where(at_loop, 1, 0) if at_loop is not None else 0)
    counts = np.bincount(kind.ravel(), minlength=3)
    present = counts > 0
    per_kind = np.where(present, kind.size / (present.sum() * np.maximum(counts, 1)), 0.0)
    return per_kind[kind].astype(np.float32)
