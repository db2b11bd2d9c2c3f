"""``eval.png``: position error over time of each evaluated trajectory."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np


def plot_errors(path: Path, series: dict[str, tuple[np.ndarray, np.ndarray]], title: str) -> None:
    """One line per trajectory: time (s) against position error (cm), its RMSE in the legend."""
    fig, ax = plt.subplots(figsize=(8, 3.5))
    for name, (t, err) in series.items():
        rmse = float(np.sqrt(np.mean(err**2))) if len(err) else float("nan")
        ax.plot(t - t[0] if len(t) else t, err * 100, lw=1, label=f"{name} (ATE RMSE {rmse * 100:.2f} cm)")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("position error (cm)")
    ax.set_title(f"position error after SE(3) alignment: {title}", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
