"""Reward-curve plots of loop-closure training runs (dissertation Fig. 3.10, 3.11)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np


def smooth(values: np.ndarray, window: int = 10) -> np.ndarray:
    if len(values) < window:
        return values
    kernel = np.ones(window) / window
    return np.convolve(np.pad(values, (window - 1, 0), mode="edge"), kernel, mode="valid")


def plot_reward_curves(curves: dict[str, list[dict]], path: str | Path, title: str) -> Path:
    """Mean episode return against environment steps, one line per run (updates without a finished episode skipped)."""
    fig, ax = plt.subplots(figsize=(7, 4), dpi=110)
    for label, curve in curves.items():
        rows = [r for r in curve if r.get("mean_return") is not None]
        if not rows:
            continue
        steps = np.array([r["step"] for r in rows])
        ax.plot(steps, smooth(np.array([r["mean_return"] for r in rows])), label=label, lw=1.4)
    ax.set_xlabel("environment steps")
    ax.set_ylabel("mean episode return (smoothed)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
