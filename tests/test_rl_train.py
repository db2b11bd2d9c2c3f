"""PPO trainer: eq. 3.20 batch length, a CleanRL-style smoke run in a subprocess, resume, ONNX parity."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from rl.batching import balance_weights, batch_length
from rl.env import GridRules, LoopClosureGrid
from rl.policy import OnnxPolicy
from rl.train_config import TrainConfig

torch = pytest.importorskip("torch", reason="the train extra (torch) is not installed")

from rl.export import export_trainer  # noqa: E402 -- imports torch: after the importorskip above
from rl.networks import RecurrentNet  # noqa: E402 -- imports torch: after the importorskip above
from rl.ppo import Trainer  # noqa: E402 -- imports torch: after the importorskip above


@torch.no_grad()
def torch_probabilities(actor: RecurrentNet, observations: np.ndarray) -> np.ndarray:
    """(T, B, 84, 84, 3) observation sequences -> (T, B, n_actions) probabilities, state carried over."""
    h, c = actor.initial_state(observations.shape[1])
    out = []
    for obs in observations:
        logits, h, c = actor.step(torch.from_numpy(obs), h, c)
        out.append(torch.softmax(logits, -1).numpy())
    return np.stack(out)


def _objslam(*args: str, timeout: float = 240) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.run(
        [sys.executable, "-m", "service", *args], env=env, capture_output=True, text=True, timeout=timeout
    )


def test_batch_length_picks_the_prefix_with_most_action_entropy():
    targets = np.zeros((40, 2), np.int64)
    targets[5, 0] = 1  # one loop closure early: short prefixes have the most balanced actions
    assert batch_length(targets, 3, 4, 40) == 6
    targets[30:34, :] = 2  # a burst later outweighs it
    assert batch_length(targets, 3, 4, 40) == 34
    assert batch_length(np.zeros((40, 2), np.int64), 3, 8, 40) == 8  # no loop closures: ties -> shortest


def test_balance_weights_give_each_kind_of_step_equal_total_weight():
    targets = np.zeros((10, 2), np.int64)
    at_loop = np.zeros((10, 2), bool)
    targets[0, 0] = 1  # one due loop closure
    at_loop[0, 0] = at_loop[1, 1] = at_loop[2, 1] = True  # ... and two first visits
    w = balance_weights(targets, at_loop)
    assert np.isclose(w.mean(), 1.0)
    due, first, other = w[0, 0], w[1, 1], w[3, 0]
    assert np.isclose(due, 2 * first) and np.isclose(due * 1, other * 17)  # equal totals: 1, 2 and 17 steps
    assert np.allclose(balance_weights(np.zeros((4, 2), np.int64), np.zeros((4, 2), bool)), 1.0)
    two = balance_weights(targets)  # due vs the rest
    assert np.isclose(two[0, 0] * 1, two[3, 0] * 19)


def test_train_lc_smoke_run_exports_a_policy_that_eval_lc_reads(tmp_path):
    out = tmp_path / "p.onnx"
    res = _objslam(
        "train-lc", "--map", "config1", "--steps", "400", "--envs", "2", "--b1", "16", "--b2", "48", "--out", str(out)
    )
    assert res.returncode == 0, res.stderr[-2000:]
    for suffix in (".onnx", ".json", ".pt", ".png"):
        assert out.with_suffix(suffix).is_file(), suffix
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["steps"] >= 400 and meta["map"]["name"] == "config1" and meta["curve"]
    res = _objslam("eval-lc", str(out), "--runs", "2", "--max-steps", "500", "--json", "--no-baselines")
    assert res.returncode == 0, res.stderr[-2000:]
    figures = json.loads(res.stdout)["config1"]
    assert set(figures) >= {"precision", "recall", "lc_due", "lc_taken", "runs"} and figures["runs"] == 2
    assert figures["lc_due"] > 0
    bad = _objslam("train-lc", "--map", "nosuchmap", "--steps", "10", "--out", str(tmp_path / "x.onnx"))
    assert bad.returncode == 1 and "cannot read map" in bad.stderr


def test_resume_continues_counters_and_curve(tmp_path):
    cfg = TrainConfig(map="config2", total_steps=200, n_envs=2, minibatches=2, b1=8, b2=24, threads=1)
    trainer = Trainer(cfg)
    trainer.train(tmp_path / "c.pt")
    steps, updates = trainer.global_step, len(trainer.curve)
    resumed = Trainer.resume(tmp_path / "c.pt", total_steps=400)
    assert resumed.global_step == steps and len(resumed.curve) == updates
    for name, p in trainer.actor.state_dict().items():
        assert torch.equal(p, resumed.actor.state_dict()[name]), name
    resumed.train(tmp_path / "c.pt")
    assert resumed.global_step >= 400 and len(resumed.curve) > updates


def test_onnx_actor_matches_torch_on_recorded_sequences(tmp_path):
    trainer = Trainer(TrainConfig(map="config3", total_steps=96, n_envs=2, minibatches=2, b1=8, b2=24, threads=1))
    trainer.train()
    envs = [LoopClosureGrid("config3", rules=GridRules(terminate=False)) for _ in range(3)]
    seq = [np.stack([env.reset(seed=i)[0] for i, env in enumerate(envs)])]
    for _ in range(40):
        seq.append(np.stack([env.step(0)[0] for env in envs]))
    observations = np.stack(seq)
    reference = torch_probabilities(trainer.actor, observations)
    assert trainer.actor.aux_head is not None  # trained with the auxiliary loss; the export leaves it out
    policy = OnnxPolicy(export_trainer(trainer, tmp_path / "p.onnx", wall_s=0.0))
    assert [i.name for i in policy.session.get_inputs()] == ["obs", "h", "c"]
    assert [o.name for o in policy.session.get_outputs()] == ["probs", "h_out", "c_out"]
    assert policy.session.get_outputs()[0].shape[-1] == 6  # config3: 5 locations + "no loop closure"
    policy.reset(3)
    got = np.stack([policy.probabilities(obs) for obs in observations])
    assert np.abs(got - reference).max() < 1e-5
    h, c = trainer.actor.initial_state(3)
    for obs in observations:  # the carried LSTM state agrees too
        _, h, c = trainer.actor.step(torch.from_numpy(obs), h, c)
    assert np.abs(policy.h - h.detach().numpy()).max() < 1e-5 and np.abs(policy.c - c.detach().numpy()).max() < 1e-5
    assert not np.allclose(reference[0], reference[-1])  # memory and views change the output over time


def test_buffer_stores_the_visited_targets_across_episode_ends():
    cfg = TrainConfig(
        map="config2", total_steps=10_000, n_envs=2, minibatches=2, b1=8, b2=96, threads=1, max_episode_steps=30
    )  # several episodes end inside one buffer
    trainer = Trainer(cfg)
    trainer.collect()
    b = trainer.buffer
    assert b.visited.shape == (96, 2, 4) and b.starts[1:].any()
    assert not b.visited[b.starts].any()  # the first step of an episode remembers nothing
    due = b.targets > 0
    assert due.any()
    assert b.visited[due, b.targets[due] - 1].all()  # a loop closure is due only where the location is remembered
    for e in range(2):  # within an episode, memory only grows
        for t in range(1, 96):
            if not b.starts[t, e]:
                assert (b.visited[t, e] >= b.visited[t - 1, e]).all(), (t, e)
    assert b.visited[~b.starts].any()


def test_aux_loss_trains_the_aux_head_and_the_lstm_but_not_the_policy_head():
    net = RecurrentNet(5, 16, aux=4)
    frames = torch.randint(0, 255, (6, 84, 84, 3), dtype=torch.uint8)
    index = torch.randint(0, 6, (7, 2))
    starts = torch.zeros(7, 2, dtype=torch.bool)
    logits, aux = net.sequence(frames, index, starts, *net.initial_state(2), with_aux=True)
    assert logits.shape == (7, 2, 5) and aux.shape == (7, 2, 4)
    assert torch.equal(logits, net.sequence(frames, index, starts, *net.initial_state(2)))
    aux.sum().backward()
    assert net.head.weight.grad is None  # the policy head only learns from the PPO objective
    assert net.aux_head.weight.grad.abs().sum() > 0 and net.lstm.weight_hh_l0.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="no auxiliary head"):
        RecurrentNet(5, 16).sequence(frames, index, starts, *net.initial_state(2), with_aux=True)

    cfg = TrainConfig(map="config2", total_steps=400, n_envs=2, minibatches=2, b1=8, b2=48, threads=1)
    assert cfg.aux_coef > 0
    trainer = Trainer(cfg)
    assert trainer.actor.aux_head.out_features == 4 and trainer.critic.aux_head is None
    before = {k: v.clone() for k, v in trainer.actor.state_dict().items()}
    trainer.train()
    losses = [row["aux_loss"] for row in trainer.curve]
    assert all(np.isfinite(losses)) and min(losses) > 0
    after = trainer.actor.state_dict()
    assert not torch.equal(before["aux_head.weight"], after["aux_head.weight"])
    assert not torch.equal(before["lstm.weight_hh_l0"], after["lstm.weight_hh_l0"])

    plain = Trainer(
        TrainConfig(map="config2", total_steps=100, n_envs=2, minibatches=2, b1=8, b2=24, threads=1, aux_coef=0.0)
    )
    assert plain.actor.aux_head is None and not any(k.startswith("aux") for k in plain.actor.state_dict())
    plain.train()
    assert all(row["aux_loss"] == 0.0 for row in plain.curve)


def test_resume_of_a_checkpoint_saved_before_the_aux_loss(tmp_path):
    cfg = TrainConfig(map="config1", total_steps=100, n_envs=2, minibatches=2, b1=8, b2=24, threads=1, aux_coef=0.0)
    Trainer(cfg).train(tmp_path / "old.pt")
    ckpt = torch.load(tmp_path / "old.pt", weights_only=False)
    del ckpt["config"]["aux_coef"]  # as written by the trainer before aux_coef existed
    torch.save(ckpt, tmp_path / "old.pt")
    resumed = Trainer.resume(tmp_path / "old.pt", total_steps=200)
    assert resumed.cfg.aux_coef == 0.0 and resumed.actor.aux_head is None
    resumed.train()
    ckpt["config"]["aux_coef"] = 1.0  # a configuration that does not match the saved networks
    torch.save(ckpt, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="does not match its configuration"):
        Trainer.resume(tmp_path / "bad.pt")


def test_place_and_action_aux_targets_and_a_warm_start_from_a_smaller_map(tmp_path):
    cfg = TrainConfig(
        map="config2",
        total_steps=200,
        n_envs=2,
        minibatches=2,
        b1=8,
        b2=24,
        threads=1,
        aux_targets="visited+place+action",
    )
    trainer = Trainer(cfg)
    L = trainer.grid.n_loops
    assert trainer.actor.aux_head.out_features == L + 2 * (L + 1)  # visit bits, location classes, action classes
    trainer.train(tmp_path / "small.pt")
    assert all(np.isfinite(row["aux_loss"]) and row["aux_loss"] > 0 for row in trainer.curve)
    b = trainer.buffer
    assert ((b.loop >= -1) & (b.loop < L)).all() and np.array_equal(b.at_loop, b.loop >= 0)

    bigger = Trainer(
        TrainConfig(
            map="config3",
            total_steps=100,
            n_envs=2,
            minibatches=2,
            b1=8,
            b2=24,
            threads=1,
            aux_targets="visited+place+action",
            init_from=str(tmp_path / "small.pt"),
        )
    )
    small = torch.load(tmp_path / "small.pt", weights_only=False)["actor"]
    own = bigger.actor.state_dict()
    assert torch.equal(own["lstm.weight_hh_l0"], small["lstm.weight_hh_l0"])  # shared shapes copied
    assert own["head.weight"].shape != small["head.weight"].shape  # 5 locations: its own policy head
    with pytest.raises(ValueError, match="aux_targets"):
        Trainer(TrainConfig(map="config2", total_steps=10, n_envs=2, minibatches=2, aux_targets="everything"))


def test_the_shipped_init_checkpoint_starts_a_trainer_for_another_map():
    """bench policy-loops and the README's two-pass workflow start from models/lc/config1.init.pt."""
    from rl.commands import INIT_CHECKPOINT, POLICY_DIR

    path = POLICY_DIR / INIT_CHECKPOINT
    shipped = torch.load(path, weights_only=False)
    trainer = Trainer(
        TrainConfig(
            map="config3", total_steps=100, n_envs=2, minibatches=2, b1=8, b2=24, threads=1, init_from=str(path)
        )
    )
    own = trainer.actor.state_dict()
    assert torch.equal(own["lstm.weight_hh_l0"], shipped["actor"]["lstm.weight_hh_l0"])
    assert torch.equal(trainer.critic.state_dict()["lstm.weight_hh_l0"], shipped["critic"]["lstm.weight_hh_l0"])
