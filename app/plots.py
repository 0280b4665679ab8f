"""Figures people would rather look at than read. Matplotlib with the Agg backend (no display needed)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from twohr.trajectory import Trajectory  # noqa: E402

#: how :func:`plot_trajectories` draws each kind of marked pose: marker, colour, size
MARK_STYLES = {"keyframe": ("D", "tab:green", 24), "masked": ("o", "tab:orange", 14), "lost": ("x", "tab:red", 30)}


def _trajectory_views(axes, gt: Trajectory | None, est: Trajectory, marks: dict[str, np.ndarray] | None) -> None:
    """Top and side views of ``est`` (and ``gt``), with start, end and the poses flagged in ``marks``."""
    for ax, (i, j, name) in zip(axes, [(0, 1, "top (x-y)"), (0, 2, "side (x-z)")], strict=True):
        if gt is not None:
            ax.plot(gt.positions[:, i], gt.positions[:, j], "k-", lw=1.5, label="ground truth")
        p = est.positions
        ax.plot(p[:, i], p[:, j], "-", color="tab:blue", lw=1.2, label="estimate")
        for label, flags in (marks or {}).items():
            marker, color, size = MARK_STYLES.get(label, ("o", "tab:purple", 14))
            flags = np.asarray(flags, bool)
            if flags.any():
                ax.scatter(p[flags, i], p[flags, j], marker=marker, color=color, s=size, lw=1.0, zorder=3,
                           label=f"{label} ({int(flags.sum())})")
        if len(p):
            ax.scatter(p[:1, i], p[:1, j], marker="o", s=70, facecolor="none", edgecolor="k", lw=1.5, zorder=4,
                       label="start")
            ax.scatter(p[-1:, i], p[-1:, j], marker="s", s=60, color="k", zorder=4, label="end")
        ax.set_xlabel("xyz"[i] + " [m]")
        ax.set_ylabel("xyz"[j] + " [m]")
        ax.set_title(name)
        ax.axis("equal")
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)


def plot_trajectories(path: str | Path, gt: Trajectory, est: Trajectory, ate: np.ndarray, title: str = "",
                      marks: dict[str, np.ndarray] | None = None) -> Path:
    """Top view, side view and ATE over time of an aligned estimate against ground truth. ``marks`` flags
    poses of ``est`` to draw (name -> bool per pose; e.g. keyframe, masked, lost); start and end are marked."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 3, figsize=(16, 5))
    _trajectory_views(axes[:2], gt, est, marks)
    t = gt.stamps - gt.stamps[0]
    axes[2].plot(t, ate, color="tab:red", lw=1.0)
    rmse = float(np.sqrt(np.mean(ate**2))) if len(ate) else float("nan")
    axes[2].axhline(rmse, color="k", ls="--", lw=0.8, label=f"RMSE {rmse:.3f} m")
    axes[2].set_xlabel("time [s]")
    axes[2].set_ylabel("ATE [m]")
    axes[2].set_title("absolute trajectory error")
    axes[2].grid(alpha=0.3)
    axes[2].legend(loc="best", fontsize=8)
    return _save(fig, path, title)


def _save(fig, path: Path, title: str = "") -> Path:
    """Title, lay out, write and close a figure."""
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_trajectory(path: str | Path, est: Trajectory, marks: dict[str, np.ndarray] | None = None,
                    title: str = "") -> Path:
    """Top and side views of a trajectory without ground truth, with start, end and marked poses."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    _trajectory_views(axes, None, est, marks)
    return _save(fig, path, title)


def plot_timeline(path: str | Path, index: np.ndarray, panels: dict[str, dict[str, np.ndarray]],
                  spans: dict[str, np.ndarray] | None = None, title: str = "") -> Path:
    """Per-frame series, one panel each (panel title -> {label: values}) over frame ``index``; ``spans`` shades
    the frames flagged in each (name -> bool per frame, e.g. lost) in every panel."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(len(panels), 1, figsize=(14, 2.6 * len(panels)), sharex=True, squeeze=False)
    colors = {"lost": "tab:red", "keyframe": "tab:green"}
    for ax, (panel, series) in zip(axes[:, 0], panels.items(), strict=True):
        for label, values in series.items():
            ax.plot(index, values, lw=1.0, label=label)
        for name, flags in (spans or {}).items():
            ax.fill_between(index, 0, 1, where=np.asarray(flags, bool), step="mid", transform=ax.get_xaxis_transform(),
                            color=colors.get(name, "tab:gray"), alpha=0.15, lw=0, label=name)
        ax.set_ylabel(panel)
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8, ncol=len(series))
    axes[-1, 0].set_xlabel("frame")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
