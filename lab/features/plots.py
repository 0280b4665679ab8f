"""Figures of the detector's studies (matplotlib, Agg backend: no display needed)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .quality import FeatureTable, StudyResult  # noqa: E402

PARAMETER_LABELS = {
    "reliability_clusters": "k for reliability (paper Fig 6)",
    "repeatability_clusters": "k for repeatability (paper Fig 7)",
    "score_threshold": "T: keep reliability × repeatability > T",
    "floors": "score floors before the filter (both)",
}


def plot_study(result: StudyResult, path: str | Path, chosen: dict[str, float] | None = None) -> Path:
    """One column per studied parameter: %Rep, %Prec and keypoints per frame against its value.

    Dotted grey lines mark raw R2D2 (no 2HR filter); vertical lines mark ``chosen`` values.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    parameters = list(dict.fromkeys(p.parameter for p in result.points))
    fig, axes = plt.subplots(3, len(parameters), figsize=(4.2 * len(parameters), 9.5), squeeze=False)
    colours = plt.cm.viridis(np.linspace(0.1, 0.8, len(result.deltas)))
    raw = result.raw_r2d2
    for col, parameter in enumerate(parameters):
        points = [p for p in result.points if p.parameter == parameter]
        x = [p.value for p in points]
        for row, metric in enumerate(("rep", "prec")):
            ax = axes[row, col]
            for colour, d in zip(colours, result.deltas, strict=True):
                ax.plot(x, [p.by_delta[str(d)][metric] for p in points], "o-", color=colour, ms=3.5, label=f"Δ={d}")
                ax.axhline(raw.by_delta[str(d)][metric], color=colour, ls=":", lw=1)
            ax.set_ylabel("%Rep" if metric == "rep" else "%Prec (mutual NN)")
        ax = axes[2, col]
        ax.plot(x, [p.keypoints_per_frame for p in points], "s-", color="tab:red", ms=3.5, label="keypoints / frame")
        ax.axhline(raw.keypoints_per_frame, color="tab:red", ls=":", lw=1)
        ax.set_ylabel("keypoints / frame", color="tab:red")
        ax.set_ylim(0, 1.1 * max([raw.keypoints_per_frame] + [p.keypoints_per_frame for p in points]))
        twin = ax.twinx()
        twin.plot(x, [100 * p.coverage for p in points], "^-", color="tab:blue", ms=3.5)
        twin.set_ylabel("grid coverage % (40 px cells)", color="tab:blue")
        twin.set_ylim(0, 100)
        axes[2, col].set_xlabel(PARAMETER_LABELS.get(parameter, parameter))
        axes[0, col].set_title(PARAMETER_LABELS.get(parameter, parameter), fontsize=10)
        for row in range(3):
            axes[row, col].grid(alpha=0.3)
            if chosen and parameter in chosen:
                axes[row, col].axvline(chosen[parameter], color="k", lw=0.8, alpha=0.6)
    axes[0, 0].legend(fontsize=8, title="dotted: raw R2D2", title_fontsize=8)
    fig.suptitle(f"2HR parameter study, one parameter changed at a time from the defaults; "
                 f"{result.frames_detected} frames of {Path(result.sequence).name} [{result.frames[0]}, "
                 f"{result.frames[1]}), {result.threshold_px:g} px", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_table(table: FeatureTable, path: str | Path) -> Path:
    """Bar charts per method and delta: %Rep with its chance level (black ticks), one-to-one %Rep, %Prec."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    panels = (("rep", "%Rep (any keypoint within the threshold)"), ("rep_1to1", "%Rep, one-to-one"),
              ("prec", "%Prec (mutual NN matches)"))
    fig, axes = plt.subplots(1, len(panels), figsize=(15, 4.2))
    width = 0.8 / len(table.rows)
    x = np.arange(len(table.deltas))
    for ax, (metric, label) in zip(axes, panels, strict=True):
        for i, row in enumerate(table.rows):
            offset = x + (i - (len(table.rows) - 1) / 2) * width
            ax.bar(offset, [row.by_delta[str(d)][metric] for d in table.deltas], width, label=row.method,
                   color=f"C{i}")
            if metric == "rep":
                chance = [row.by_delta[str(d)].get("rep_chance", np.nan) for d in table.deltas]
                ax.plot(offset, chance, "_", color="k", ms=12, mew=2, label="chance level" if i == 0 else None)
        ax.set_xticks(x, [f"Δ={d}" for d in table.deltas])
        ax.set_title(label, fontsize=10)
        ax.set_ylim(0, 100)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=8, ncol=2)
    fig.suptitle(f"Feature quality on {Path(table.sequence).name}, frames [{table.frames[0]}, {table.frames[1]}), "
                 f"{table.threshold_px:g} px; chance level = %Rep with reprojections moved 10 px", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
