"""The policy proposer of the live service (rl/proposer.py) on the shipped room_seed3 policy, fed the true
keyframe poses of the synthetic room it was trained for."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import pytest

from rl.policy import OnnxPolicy
from rl.proposer import PolicyProposer
from service.persistence import decode, encode
from sources import open_dataset
from tests.conftest import ROOM_POLICY, requires_room_policy

POLICY = ROOM_POLICY


@requires_room_policy
def test_loop_closure_actions_hold_for_the_step_and_propose_older_keyframes_nearest_first():
    poses = open_dataset("synthetic:room?seed=3&frames=300").ground_truth.poses[::3]  # the keyframes
    proposer = PolicyProposer(OnnxPolicy(POLICY), radius=1, max_candidates=3)
    cells, steps, out = [], [], []
    for kf, pose in enumerate(poses):
        out.append(proposer.observe(kf, pose))
        cells.append(tuple(int(v) for v in proposer.frame.cells(pose[:3, 3][None])[0]))
        steps.append(proposer.steps)
    changes = sum(a != b for a, b in pairwise(cells)) + 1
    assert proposer.steps == changes and len(proposer.inference_s) == changes  # one policy run per step
    proposals = [(kf, p) for kf, p in enumerate(out) if p is not None]
    assert any(p.candidates for _, p in proposals), "the trained policy closes no loop on its own room"
    for kf, p in proposals:
        # the action of a step holds until the camera leaves the cell
        nxt = kf + 1
        if nxt < len(poses) and cells[nxt] == cells[kf]:
            assert out[nxt] is not None and (out[nxt].step, out[nxt].location) == (p.step, p.location)
        target = proposer.policy.grid.loops[p.location]
        costs = []
        for c in p.candidates:
            assert c < kf and steps[c] < p.step - proposer.exclude_last  # older than the excluded last steps
            assert max(abs(cells[c][0] - target[0]), abs(cells[c][1] - target[1])) <= 1  # at the location
            angle = np.arccos(np.clip(poses[c][:3, 2] @ poses[kf][:3, 2], -1, 1))
            same = proposer.frame.heading(poses[c][:3, :3]) == proposer.frame.heading(poses[kf][:3, :3])
            costs.append((not same, np.linalg.norm(poses[c][:3, 3] - poses[kf][:3, 3]) + 0.5 * angle))
        assert costs == sorted(costs) and len(p.candidates) <= 3


@requires_room_policy
def test_a_proposer_restored_from_a_snapshot_continues_exactly():
    poses = open_dataset("synthetic:room?seed=3&frames=300").ground_truth.poses[::3]
    first, half = PolicyProposer(OnnxPolicy(POLICY)), len(poses) // 2
    for kf in range(half):
        first.observe(kf, poses[kf])
    resumed = PolicyProposer(OnnxPolicy(POLICY))
    resumed.restore(decode(b"".join(encode({"proposer": first.state()})))["proposer"])  # the snapshot codec
    rest = [(first.observe(kf, poses[kf]), resumed.observe(kf, poses[kf])) for kf in range(half, len(poses))]
    assert any(a is not None and a.candidates for a, _ in rest)  # the second half proposes loop closures
    for a, b in rest:
        assert (a is None) == (b is None)
        if a is not None:
            assert (a.step, a.location, a.cell, a.candidates) == (b.step, b.location, b.cell, b.candidates)
            assert a.probability == pytest.approx(b.probability, abs=1e-6)
