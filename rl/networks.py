"""Actor and critic networks of the loop-closure policy (dissertation Sec. 3.6, Fig. 3.8).

Each is its own network (dual design): three convolutions over the 84 x 84 observation, a linear
layer, an LSTM cell that carries memory of the places seen, and a linear head.
"""

from __future__ import annotations

import itertools
from typing import TypeVar

import numpy as np
import torch
from torch import nn

Layer = TypeVar("Layer", nn.Linear, nn.Conv2d)


def _init(layer: Layer, gain: float = np.sqrt(2)) -> Layer:
    nn.init.orthogonal_(layer.weight, gain)
    if layer.bias is not None:  # every layer here has one
        nn.init.zeros_(layer.bias)
    return layer


def to_input(obs: torch.Tensor) -> torch.Tensor:
    """(..., 84, 84, 3) uint8 images -> (N, 3, 84, 84) floats in [0, 1]."""
    return obs.reshape(-1, *obs.shape[-3:]).permute(0, 3, 1, 2).float() / 255.0


def input_pool(grid_shape: tuple[int, int], size: int = 84) -> int:
    """Average-pooling factor applied to the observation: the image holds no more detail than the grid."""
    cells = max(grid_shape)
    return 4 if cells * 4 <= size else 2 if cells * 2 <= size else 1


class RecurrentNet(nn.Module):
    """3 conv layers + LSTM + linear head; ``out`` = number of actions (actor) or 1 (critic).

    ``pool`` shrinks the 84 x 84 input first (1, 2 or 4); the first convolution's kernel and stride are
    scaled to match, so every variant sees the image at the same field of view.

    ``aux`` > 0 adds ``aux_head``, a second linear layer on the LSTM output with that many logits, for an
    auxiliary training loss (rl/auxiliary.py: the visit memory); ``step`` and the ONNX export do not use it.
    """

    def __init__(self, out: int, hidden: int = 128, head_gain: float = 0.01, pool: int = 1, aux: int = 0):
        super().__init__()
        self.hidden = hidden
        kernel, stride = {1: (8, 4), 2: (4, 2), 4: (3, 1)}[pool]
        convs = nn.Sequential(
            nn.AvgPool2d(pool) if pool > 1 else nn.Identity(),
            _init(nn.Conv2d(3, 16, kernel, stride=stride)),
            nn.ReLU(),
            _init(nn.Conv2d(16, 32, 4, stride=2)),
            nn.ReLU(),
            _init(nn.Conv2d(32, 32, 3, stride=1)),
            nn.ReLU(),
            nn.Flatten(),
        )
        with torch.no_grad():
            n_flat = convs(torch.zeros(1, 3, 84, 84)).shape[1]
        self.encoder = nn.Sequential(*convs, _init(nn.Linear(n_flat, 256)), nn.ReLU())
        self.lstm = nn.LSTM(256, hidden)  # one layer; stepped one time step at a time when acting
        for name, p in self.lstm.named_parameters():
            if "bias" in name:
                nn.init.zeros_(p)
            else:
                nn.init.orthogonal_(p, 1.0)
        self.head = _init(nn.Linear(hidden, out), head_gain)
        self.aux_head = _init(nn.Linear(hidden, aux), 1.0) if aux > 0 else None

    def initial_state(self, batch: int) -> tuple[torch.Tensor, torch.Tensor]:
        z = torch.zeros(batch, self.hidden)
        return z, z.clone()

    def step(self, obs: torch.Tensor, h: torch.Tensor, c: torch.Tensor):
        """One time step for a batch: (B, 84, 84, 3) uint8 -> (B, out), new (h, c)."""
        out, (h, c) = self.lstm(self.encoder(to_input(obs)).unsqueeze(0), (h.unsqueeze(0), c.unsqueeze(0)))
        return self.head(out[0]), h[0], c[0]

    def sequence(
        self,
        frames: torch.Tensor,
        index: torch.Tensor,
        starts: torch.Tensor,
        h: torch.Tensor,
        c: torch.Tensor,
        with_aux: bool = False,
    ):
        """Outputs over (T, B) steps whose observations are ``frames[index]``, from state (h, c).

        Passing each distinct image once (``frames``) and its uses (``index``) gives the same result as
        passing all T * B images, at the cost of the distinct ones. Memory is reset where ``starts`` is set.
        ``with_aux`` returns (outputs, auxiliary head outputs).
        """
        T, B = starts.shape
        features = self.encoder(to_input(frames))[index.reshape(-1)].reshape(T, B, -1)
        keep = (~starts).float().unsqueeze(-1)
        # the fused LSTM runs over spans without episode starts; memory is cut at each start
        cuts = [0, *sorted(set(torch.nonzero(starts.any(dim=1)).flatten().tolist()) - {0}), T]
        h, c = h.unsqueeze(0), c.unsqueeze(0)
        outputs = []
        for a, b in itertools.pairwise(cuts):
            out, (h, c) = self.lstm(features[a:b], (h * keep[a], c * keep[a]))
            outputs.append(out)
        lstm_out = torch.cat(outputs)
        if with_aux:
            if self.aux_head is None:
                raise ValueError("this network has no auxiliary head (aux=0)")
            return self.head(lstm_out), self.aux_head(lstm_out)
        return self.head(lstm_out)


class OnnxActor(nn.Module):
    """The actor as one exported step: (obs uint8, h, c) -> (action probabilities, h, c)."""

    def __init__(self, actor: RecurrentNet):
        super().__init__()
        self.actor = actor

    def forward(self, obs: torch.Tensor, h: torch.Tensor, c: torch.Tensor):
        logits, h, c = self.actor.step(obs, h, c)
        return torch.softmax(logits, dim=-1), h, c
