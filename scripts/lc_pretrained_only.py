"""eval-lc figures of a loop-closure policy right after memory pretraining with the imitation start, before
any PPO step: how much of a shipped policy's figure PPO adds (docs/rl.md, "Imitation start").

Usage: python scripts/lc_pretrained_only.py configN [--epochs 40] [--out DIR]

Same networks, seeds and pretraining as `objslam train-lc --map configN --aux-targets visited+place+action
--episode-steps 512 --threads 1 --pretrain-epochs N --pretrain-walks 512 --pretrain-length 128
--pretrain-policy --balance-first-visits` up to its first PPO step (the pretraining is deterministic on one
thread: its history matches the shipped policy's JSON), then the eval-lc protocol (20 runs, seed 10000,
20,000 steps at most) on the exported ONNX policy. Prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rl.evaluate import evaluate
from rl.export import export_actor
from rl.policy import OnnxPolicy
from rl.ppo import Trainer
from rl.pretrain import MemoryPretrainer, PretrainConfig
from rl.train_config import TrainConfig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("map")
    ap.add_argument("--epochs", type=int, default=40)
    ap.add_argument("--out", type=Path, default=Path("/tmp"))
    args = ap.parse_args()
    cfg = TrainConfig(
        map=args.map,
        seed=0,
        threads=1,
        max_episode_steps=512,
        aux_targets="visited+place+action",
        balance_first_visits=True,
    )
    trainer = Trainer(cfg)
    history = MemoryPretrainer(
        trainer, PretrainConfig(epochs=args.epochs, walks=512, length=128, seed=0, policy_from_aux=True)
    ).run()
    path = export_actor(
        trainer.actor,
        args.out / f"{args.map}_pretrained_only.onnx",
        {"map": trainer.grid.to_json(), "exclude_last": cfg.exclude_last, "steps": 0},
    )
    policy = OnnxPolicy(path)
    result = evaluate(policy.grid, policy, runs=20, seed=10_000, max_steps=20_000, exclude_last=cfg.exclude_last)
    print(
        json.dumps(
            {
                "config": args.map,
                "precision": result.precision,
                "recall": result.recall,
                "lc_taken": result.lc_taken,
                "lc_due": result.lc_due,
                "pretrain_last_epoch": history[-1],
            }
        )
    )


if __name__ == "__main__":
    main()
