"""``objslam bench lc-batch``: the batch-size ablation of Fig. 3.10 (fixed 512, fixed 2048, entropy-based).

Three PPO runs on one grid configuration with the same seed and step budget; the batch is the total over
the 8 actors (512 = 8 x 64 steps, 2048 = 8 x 256, entropy-based: 8 x n*, n* in [64, 256] by eq. 3.20).
Each trained policy is evaluated with the Table 3.1 protocol; the reward curves go into one PNG.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

from rich.console import Console

from bench.report import markdown_table, record, show_table
from rl.plot import plot_reward_curves

VARIANTS: dict[str, dict[str, Any]] = {  # label -> TrainConfig fields
    "fixed 512": {"batch": "fixed", "n_steps": 64},
    "fixed 2048": {"batch": "fixed", "n_steps": 256},
    "entropy-based (64-256 per actor)": {"batch": "entropy", "b1": 64, "b2": 256},
}


def run_batch_ablation(console: Console, grid_name: str, steps: int, plot: Path, write: Path | None) -> None:
    from rl.evaluate import evaluate
    from rl.export import export_trainer
    from rl.policy import OnnxPolicy
    from rl.ppo import Trainer
    from rl.train_config import TrainConfig

    curves, rows = {}, []
    for label, overrides in VARIANTS.items():
        console.print(f"training {grid_name}, {label} ...")
        trainer = Trainer(TrainConfig(map=grid_name, total_steps=steps, max_episode_steps=128, threads=1, **overrides))
        result = trainer.train()
        curves[label] = trainer.curve
        with tempfile.TemporaryDirectory() as tmp:
            policy = OnnxPolicy(export_trainer(trainer, Path(tmp) / "p.onnx", result.wall_s))
            res = evaluate(trainer.grid, policy)
        batches = [r["batch_length"] * trainer.cfg.n_envs for r in trainer.curve]
        returns = [r["mean_return"] for r in trainer.curve[-10:] if r["mean_return"] is not None]
        rows.append(
            [
                label,
                f"{min(batches)}-{max(batches)}",
                len(trainer.curve),
                f"{sum(returns) / len(returns):.0f}" if returns else "-",
                f"{100 * res.precision:.1f} / {100 * res.recall:.1f}",
                f"{result.wall_s:.0f}",
            ]
        )
    plot_reward_curves(curves, plot, f"batch-size ablation on {grid_name} ({steps} steps)")
    header = ["batch", "batch size (steps)", "updates", "mean return, last 10 updates", "eval P / R %", "wall s"]
    show_table(console, f"Batch-size ablation (Fig. 3.10) on {grid_name}", header, rows)
    record(
        "lc-batch",
        "RL loop closure: batch-size ablation (Fig. 3.10)",
        f"objslam bench lc-batch --map {grid_name} --steps {steps}",
        markdown_table(header, rows),
        f"Reward curves: `{plot}`. Same seed, balanced loss and step budget in each run; evaluation as in "
        "eval-lc (20 runs).",
        write,
    )
