"""Auxiliary visit-memory loss of the loop-closure actor (``aux_coef``; rl/ppo.py, rl/pretrain.py).

An UNREAL-style auxiliary task with privileged simulator information. Whether a loop closure is due
depends on memory: the current location must have been first visited more than c steps ago. From the
sparse PPO reward alone the LSTM did not learn it, and the policies also closed "loops" on first visits.
The environment reports that memory in ``info["visited"]`` (one bit per location); the actor has a second
linear head on its LSTM output (``aux_head``, n_loops logits) trained at every step with binary
cross-entropy against it, weighted by ``aux_coef`` and added to the PPO loss. The gradient reaches the
encoder and LSTM, not the policy head, which the PPO objective alone trains; the critic is unchanged.
Acting, the ONNX export and evaluation never use the aux head. ``aux_targets="visited+here+due"`` adds,
per location, "the agent stands on it" and "a loop closure is due there" (= here and visited) to the aux
head's targets: the recognition of the location and the conjunction a linear policy head needs, as
features of the LSTM output (on maps with many locations the visit memory alone was not learned).
``aux_targets="visited+place+action"`` adds instead two (n_loops + 1)-way classifiers: the location stood
on (or none) and the correct action. The policy head is still trained by the PPO objective only.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from rl.batching import balance_weights

# aux_targets -> aux logits: (per location, extra); "visited+place+action" adds two (n_loops + 1)-way classifiers
AUX_TARGETS = {"visited": (1, 0), "visited+here+due": (3, 0), "visited+place+action": (3, 2)}


def aux_outputs(aux_targets: str, n_loops: int) -> int:
    """Number of logits of the aux head for these targets on a map with ``n_loops`` locations."""
    per_location, extra = AUX_TARGETS[aux_targets]
    return n_loops * per_location + extra


def aux_action_outputs(n_loops: int) -> slice:
    """Where the correct-action classifier's L + 1 logits sit among the aux head's "visited+place+action"
    outputs: after the L visit bits and the L + 1 place logits."""
    return slice(2 * n_loops + 1, 3 * n_loops + 2)


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


def aux_bits(aux_targets: str, n_loops: int, visited: np.ndarray, loop: np.ndarray) -> np.ndarray:
    """Binary targets of the auxiliary head from per-step visit bits (..., L) and location stood on (...)."""
    if aux_targets != "visited+here+due":
        return visited.astype(np.float32)
    here = loop[..., None] == np.arange(n_loops)
    return np.concatenate([visited, here, here & visited], axis=-1).astype(np.float32)


def aux_loss(
    aux_targets: str,
    n_loops: int,
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
    L = n_loops
    if aux_targets != "visited+place+action":
        return nn.functional.binary_cross_entropy_with_logits(aux_logits, bits)
    bce = nn.functional.binary_cross_entropy_with_logits(aux_logits[..., :L], bits)
    ce = nn.functional.cross_entropy
    place_loss = ce(aux_logits[..., L : 2 * L + 1].reshape(-1, L + 1), place.reshape(-1), reduction="none")
    action_loss = ce(aux_logits[..., aux_action_outputs(L)].reshape(-1, L + 1), action.reshape(-1), reduction="none")
    return bce + (place_w.reshape(-1) * place_loss).mean() + (action_w.reshape(-1) * action_loss).mean()
