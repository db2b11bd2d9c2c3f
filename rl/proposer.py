"""Loop-closure proposals from a grid-world policy on a live map (dissertation Sec. 3.8, SPEC 6.9).

Each keyframe's pose estimate is projected into the grid world the policy was trained on. When the
camera enters a new cell the agent has taken a step: its cone-of-vision observation is rendered from
that cell and heading, the policy runs once (its LSTM state carried over), and a loop-closure action
for location l proposes the earlier keyframes recorded at l's cell (and its neighbours within
``radius`` cells), older than the last ``exclude_last`` steps, as candidates for geometric verification.
The action holds for the whole step: every further keyframe taken in the same cell proposes again (a
handheld camera often reaches the view that matches an earlier one only a few keyframes after entering
the cell). Candidates are ranked by the grid heading (the same first), then by how close the earlier
keyframe's pose estimate is to the current one (position, plus viewing direction at 0.5 m per radian).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

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
        self._active: Proposal | None = None  # the loop-closure action of the current step, if any
        # cell -> (keyframe, step, heading, position, viewing direction)
        self._visits: dict[tuple[int, int], list[tuple[int, int, int, np.ndarray, np.ndarray]]] = {}

    def state(self) -> dict:
        """Plain state to resume from: steps, the current cell and its action, the visits, the LSTM state."""
        return {
            "steps": self.steps,
            "cell": self._cell,
            "active": self._active,
            "visits": self._visits,
            "h": self.policy.h,
            "c": self.policy.c,
        }

    def restore(self, state: dict) -> None:
        self.steps, self._cell, self._active = state["steps"], state["cell"], state["active"]
        self._visits = state["visits"]
        self.policy.h, self.policy.c = state["h"], state["c"]

    def observe(self, keyframe: int, pose: np.ndarray) -> Proposal | None:
        """Record the keyframe at its cell; on entering a new cell run the policy; while its loop-closure
        action holds (the same cell), propose candidates for this keyframe."""
        row, col = self.frame.cells(pose[:3, 3][None])[0]
        cell = (int(row), int(col))
        if not self.frame.inside(np.array([cell]))[0]:
            self._active = None
            return None  # off the trained map: the policy has nothing to say
        heading = self.frame.heading(pose[:3, :3])
        if cell != self._cell:
            self._cell = cell
            self.steps += 1
            t0 = time.perf_counter()
            probs = self.policy.probabilities(self.renderer.observation(cell, heading)[None])[0]
            self.inference_s.append(time.perf_counter() - t0)
            action = int(np.argmax(probs))
            self._active = None if action == 0 else Proposal(self.steps, action - 1, cell, float(probs[action]), [])
        proposal = None
        if self._active is not None:
            target = self.policy.grid.loops[self._active.location]
            proposal = replace(self._active, candidates=self._candidates(target, heading, pose))
        self._visits.setdefault(cell, []).append(
            (keyframe, self.steps, heading, pose[:3, 3].copy(), pose[:3, 2].copy())
        )
        return proposal

    def _candidates(self, target: tuple[int, int], heading: int, pose: np.ndarray) -> list[int]:
        """Older keyframes at the proposed location: the same heading first, then the nearest in pose."""
        exclude = self.exclude_last
        assert exclude is not None  # resolved from the policy's metadata in __post_init__
        found = []
        for dr in range(-self.radius, self.radius + 1):
            for dc in range(-self.radius, self.radius + 1):
                for kf, step, h, position, forward in self._visits.get((target[0] + dr, target[1] + dc), []):
                    if step < self.steps - exclude:
                        # the angle between the viewing directions (not graph.geometry.rotation_angle of the
                        # relative rotation, which also counts roll about the optical axis)
                        angle = float(np.arccos(np.clip(forward @ pose[:3, 2], -1.0, 1.0)))
                        found.append((h != heading, float(np.linalg.norm(position - pose[:3, 3])) + 0.5 * angle, kf))
        found.sort()
        out: list[int] = []
        for *_, kf in found:
            if kf not in out:
                out.append(kf)
            if len(out) >= self.max_candidates:
                break
        return out
