"""Loop-closure proposals from a grid-world policy on a live map (dissertation Sec. 3.8, SPEC 6.9).

Each keyframe's pose estimate is projected into the grid world the policy was trained on. When the
camera enters a new cell the agent has taken a step: its cone-of-vision observation is rendered from
that cell and heading, the policy runs once (its LSTM state carried over), and a loop-closure action
for location l proposes the earlier keyframes recorded at l's cell (and its neighbours within
``radius`` cells), older than the last ``exclude_last`` steps, as candidates for geometric verification.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from rl.gridmap import MapError
from rl.map_to_grid import GroundFrame
from rl.policy import OnnxPolicy
from rl.vision import renderer_for


@dataclass
class Proposal:
    """A loop-closure action of the policy and the keyframes it points at."""

    step: int
    location: int  # 0-based loop-closure location
    cell: tuple[int, int]  # where the agent stood
    probability: float
    candidates: list[int]


@dataclass
class PolicyProposer:
    policy: OnnxPolicy
    radius: int = 1
    max_candidates: int = 3
    exclude_last: int | None = None  # default: the policy's own training rule
    steps: int = 0
    proposals: list[Proposal] = field(default_factory=list)
    inference_s: list[float] = field(default_factory=list)

    def __post_init__(self) -> None:
        if "frame" not in self.policy.grid.meta:
            raise MapError("the policy's map has no ground frame: train it with `train-lc --from-map`")
        self.frame = GroundFrame.from_json(self.policy.grid.meta["frame"])
        self.renderer = renderer_for(self.policy.grid)
        if self.exclude_last is None:
            self.exclude_last = int(self.policy.meta.get("exclude_last", 4))
        self.policy.reset(1)
        self._cell: tuple[int, int] | None = None
        self._visits: dict[tuple[int, int], list[tuple[int, int, int]]] = {}  # cell -> (keyframe, step, heading)

    def observe(self, keyframe: int, pose: np.ndarray) -> Proposal | None:
        """Record the keyframe at its cell; on entering a new cell run the policy and maybe propose."""
        cell = tuple(int(v) for v in self.frame.cells(pose[:3, 3][None])[0])
        if not self.frame.inside(np.array([cell]))[0]:
            return None  # off the trained map: the policy has nothing to say
        heading = self.frame.heading(pose[:3, :3])
        if cell == self._cell:
            self._visits.setdefault(cell, []).append((keyframe, self.steps, heading))
            return None
        self._cell = cell
        self.steps += 1
        t0 = time.perf_counter()
        probs = self.policy.probabilities(self.renderer.observation(cell, heading)[None])[0]
        self.inference_s.append(time.perf_counter() - t0)
        self._visits.setdefault(cell, []).append((keyframe, self.steps, heading))
        action = int(np.argmax(probs))
        if action == 0:
            return None
        target = self.policy.grid.loops[action - 1]
        proposal = Proposal(self.steps, action - 1, cell, float(probs[action]),
                            self._candidates(target, heading))
        self.proposals.append(proposal)
        return proposal

    def _candidates(self, target: tuple[int, int], heading: int) -> list[int]:
        """Older keyframes at the proposed location, same heading first, then nearest the location."""
        found = []
        for dr in range(-self.radius, self.radius + 1):
            for dc in range(-self.radius, self.radius + 1):
                for kf, step, h in self._visits.get((target[0] + dr, target[1] + dc), []):
                    if step < self.steps - self.exclude_last:
                        found.append((h != heading, abs(dr) + abs(dc), step, kf))
        found.sort()
        out: list[int] = []
        for *_, kf in found:
            if kf not in out:
                out.append(kf)
            if len(out) >= self.max_candidates:
                break
        return out
