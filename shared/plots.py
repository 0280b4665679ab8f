"""Figures people would rather look at than read. Matplotlib with the Agg backend (no display needed)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .trajectory import Trajectory  # noqa: E402


def plot_trajectories(path: str | Path, gt: Trajectory, est: Trajectory, ate: np.ndarray, title: str = "") -> Path:
    """Top view, side view and ATE over time of an aligned estimate against ground truth."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 3, figsize=(16, 5))
    for ax, (i, j, name) in zip(axes[:2], [(0, 1, "top (x-y)"), (0, 2, "side (x-z)")], strict=True):
        ax.plot(gt.positions[:, i], gt.positions[:, j], "k-", lw=1.5, label="ground truth")
        ax.plot(est.positions[:, i], est.positions[:, j], "-", color="tab:blue", lw=1.2, label="estimate")
        ax.set_xlabel("xyz"[i] + " [m]")
        ax.set_ylabel("xyz"[j] + " [m]")
        ax.set_title(name)
        ax.axis("equal")
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    t = gt.stamps - gt.stamps[0]
    axes[2].plot(t, ate, color="tab:red", lw=1.0)
    rmse = float(np.sqrt(np.mean(ate**2))) if len(ate) else float("nan")
    axes[2].axhline(rmse, color="k", ls="--", lw=0.8, label=f"RMSE {rmse:.3f} m")
    axes[2].set_xlabel("time [s]")
    axes[2].set_ylabel("ATE [m]")
    axes[2].set_title("absolute trajectory error")
    axes[2].grid(alpha=0.3)
    axes[2].legend(loc="best", fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
