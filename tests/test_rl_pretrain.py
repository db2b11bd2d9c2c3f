"""Supervised pretraining of the policy's visit memory on random walks (rl/pretrain.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from rl.gridmap import GridMap
from rl.train_config import TrainConfig

torch = pytest.importorskip("torch", reason="the train extra (torch) is not installed")

from rl.ppo import Trainer  # noqa: E402 -- imports torch: after the importorskip above
from rl.pretrain import (  # noqa: E402 -- imports torch: after the importorskip above
    MemoryPretrainer,
    PretrainConfig,
    Walks,
    action_logits,
    memory_scores,
    record_walks,
)
from rl.rollout import distinct_frames  # noqa: E402 -- imports torch: after the importorskip above


def test_recorded_walks_are_seeded_and_a_loop_closure_is_due_exactly_where_the_visit_bit_is_set():
    grid = GridMap.load("config2")
    walks = record_walks(grid, n=6, length=80, seed=3)
    again = record_walks(grid, n=6, length=80, seed=3)
    assert np.array_equal(walks.obs, again.obs) and np.array_equal(walks.loop, again.loop)
    assert not np.array_equal(walks.loop, record_walks(grid, n=6, length=80, seed=4).loop)
    on = walks.loop >= 0
    assert on.any() and (walks.action[~on] == 0).all()
    t, n = np.nonzero(on)
    assert np.array_equal(walks.action[t, n] > 0, walks.visited[t, n, walks.loop[t, n]])
    assert (walks.action[t, n][walks.action[t, n] > 0] == walks.loop[t, n][walks.action[t, n] > 0] + 1).all()
    assert not walks.visited[0].any() and (np.diff(walks.visited.astype(int), axis=0) >= 0).all()  # memory only grows


def test_memory_scores_count_the_bit_of_the_location_stood_on():
    loop = np.array([[0, -1, 1, 1]]).T  # (T=4, N=1): on location 0, nowhere, on location 1 twice
    action = np.array([[1, 0, 0, 2]]).T  # due at t=0 (location 0) and t=3 (location 1); t=2 is a first visit
    walks = Walks(np.zeros((4, 1, 84, 84, 3), np.uint8), np.zeros((4, 1, 2), bool), loop, action)
    logits = torch.full((4, 1, 2 * 3 + 2), -5.0)
    logits[0, 0, 0] = 5.0  # bit of location 0 set at t=0: due recalled
    logits[2, 0, 1] = 5.0  # bit of location 1 set at t=2: the first visit is not recognised
    logits[1, 0, 1] = 5.0  # a bit set where the agent stands on no location does not count
    logits[0, 0, 2 * 2 + 1 + 1] = 5.0  # action classifier: loop closure at location 0 at t=0 (correct)
    logits[2, 0, 2 * 2 + 1 + 2] = 5.0  # and at location 1 at t=2 (a first visit: wrong); "none" elsewhere
    logits[1:, 0, 2 * 2 + 1] = 1.0
    scores = memory_scores(logits, walks, n_loops=2)
    assert scores == {
        "due_recalled": 0.5,
        "first_visits_recognised": 0.0,
        "due_visits": 2,
        "other_visits": 1,
        "action_precision": 0.5,
        "action_recall": 0.5,
    }


def test_pretraining_teaches_the_lstm_the_visit_memory_and_starts_the_critic_with_it():
    trainer = Trainer(
        TrainConfig(map="config1", n_envs=2, minibatches=2, threads=1, aux_targets="visited+place+action")
    )
    untouched_head = trainer.actor.head.weight.detach().clone()
    cfg = PretrainConfig(epochs=12, walks=96, length=64, held_out=24, seed=0)
    pretrainer = MemoryPretrainer(trainer, cfg)
    history = pretrainer.run()
    assert len(history) == cfg.epochs and history[-1]["loss"] < 0.5 * history[0]["loss"]
    last = history[-1]
    assert last["due_visits"] > 20 and last["other_visits"] > 20
    # the decisive bit, set on due visits and clear on first visits: a bit blind to which places were visited
    # is set on both kinds of visit alike, so its two shares add up to about 1
    assert last["due_recalled"] + last["first_visits_recognised"] >= 1.5, last
    assert min(last["due_recalled"], last["first_visits_recognised"]) >= 0.65, last
    assert torch.equal(trainer.actor.head.weight, untouched_head)  # the policy head is left to PPO
    for name, p in trainer.actor.lstm.state_dict().items():
        assert torch.equal(p, trainer.critic.lstm.state_dict()[name]), name
    for name, p in trainer.actor.encoder.state_dict().items():
        assert torch.equal(p, trainer.critic.encoder.state_dict()[name]), name


def test_pretraining_needs_the_auxiliary_head_with_its_action_classifier():
    trainer = Trainer(TrainConfig(map="config1", n_envs=2, minibatches=2, threads=1, aux_coef=0.0))
    with pytest.raises(ValueError, match="auxiliary head"):
        MemoryPretrainer(trainer, PretrainConfig(epochs=1))
    trainer = Trainer(TrainConfig(map="config1", n_envs=2, minibatches=2, threads=1, aux_targets="visited"))
    with pytest.raises(ValueError, match="visited\\+place\\+action"):
        MemoryPretrainer(trainer, PretrainConfig(epochs=1))


def test_policy_from_aux_starts_the_policy_as_the_action_classifier():
    trainer = Trainer(
        TrainConfig(map="config2", n_envs=2, minibatches=2, threads=1, aux_targets="visited+place+action")
    )
    MemoryPretrainer(trainer, PretrainConfig(epochs=1, walks=8, length=32, held_out=2, policy_from_aux=True)).run()
    walks = record_walks(trainer.grid, n=3, length=40, seed=77)
    actor = trainer.actor
    with torch.no_grad():
        frames, index = distinct_frames(walks.obs)
        starts = torch.zeros(40, 3, dtype=torch.bool)
        starts[0] = True
        policy, aux = actor.sequence(frames, index, starts, *actor.initial_state(3), with_aux=True)
    classifier = action_logits(aux, trainer.grid.n_loops)
    assert policy.shape == classifier.shape == (40, 3, trainer.grid.n_loops + 1)
    # the same weights on the same features, through matrix products of different shapes (the classifier is a
    # slice of the auxiliary head's): equal up to float32 rounding, which depends on the CPU's GEMM kernels
    torch.testing.assert_close(policy, classifier, rtol=1e-4, atol=1e-6)
    assert policy.std() > 0.1  # a copy, not the near-uniform fresh head


def test_train_lc_pretrains_then_runs_ppo_and_records_the_pretraining_and_the_loss_balance(tmp_path):
    out = tmp_path / "p.onnx"
    args = [
        sys.executable,
        "-m",
        "service",
        "train-lc",
        "--map",
        "config1",
        "--steps",
        "200",
        "--envs",
        "2",
        "--b1",
        "16",
        "--b2",
        "48",
        "--aux-targets",
        "visited+place+action",
        "--pretrain-epochs",
        "2",
        "--pretrain-walks",
        "16",
        "--pretrain-length",
        "48",
        "--balance-first-visits",
        "--pretrain-policy",
        "--out",
        str(out),
    ]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    res = subprocess.run(args, env=env, capture_output=True, text=True, timeout=240)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "visit memory after 2 epochs" in res.stdout
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["pretrain"]["config"]["walks"] == 16 and len(meta["pretrain"]["history"]) == 2
    assert meta["pretrain"]["config"]["policy_from_aux"] is True
    assert 0 <= meta["pretrain"]["history"][-1]["action_recall"] <= 1
    assert meta["steps"] >= 200 and meta["train"]["balance_first_visits"] is True
    bad = subprocess.run([*args, "--resume"], env=env, capture_output=True, text=True, timeout=120)
    assert bad.returncode == 1 and "--resume" in bad.stderr
    at = args.index("--pretrain-epochs")
    no_pretraining = args[:at] + args[at + 2 :]
    bad = subprocess.run(no_pretraining, env=env, capture_output=True, text=True, timeout=120)
    assert bad.returncode == 1 and "--pretrain-policy needs --pretrain-epochs" in bad.stderr
    resume = [sys.executable, "-m", "service", "train-lc", "--steps", "400", "--resume", "--out", str(out)]
    res = subprocess.run(resume, env=env, capture_output=True, text=True, timeout=240)
    assert res.returncode == 0, res.stderr[-2000:]
    resumed = json.loads(out.with_suffix(".json").read_text())
    assert resumed["steps"] >= 400 and resumed["pretrain"] == meta["pretrain"]  # carried in the checkpoint
    assert resumed["wall_s"] > meta["wall_s"]  # wall time of all segments
