"""The report of ``twohr run``: the marked trajectory plot, the per-frame timeline and ``report.html``.

``report.html`` sums the run up (frames, tracked %, FPS, ATE, ms per stage) and links everything the run
wrote: the plots, ``stats.csv``, ``summary.json``, ``config.yaml`` and the trajectories.
"""

from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np

from twohr.trajectory import Trajectory
from twohr_services.tracker.stages import FrameStats
from twohr_services.tracker.trajectory import TRACKED_STATUSES

from .plots import plot_timeline, plot_trajectories, plot_trajectory


def keyframe_indices(result) -> set[int] | None:
    """The frames that became keyframes, from a :class:`~twohr_app.pipeline.RunResult`'s keyframe jobs
    (the camera-rate schedule; there a frame's ``keyframe`` stat only says it asked for one); None: use the stats."""
    return {job.index for job in result.keyframe_log if job.keyframe} if result.keyframe_log else None


def frame_flags(stats: list[FrameStats], keyframes: set[int] | None = None) -> dict[str, np.ndarray]:
    """Per frame: was it a keyframe (in ``keyframes`` if given), tracked with a dynamic mask, or lost?"""
    is_keyframe = [s.keyframe if keyframes is None else s.index in keyframes for s in stats]
    return {"keyframe": np.array(is_keyframe, bool),
            "masked": np.array([s.mask_percent > 0 for s in stats], bool),
            "lost": np.array([s.status not in TRACKED_STATUSES for s in stats], bool)}


def flags_for(trajectory: Trajectory, stats: list[FrameStats], keyframes: set[int] | None = None
              ) -> dict[str, np.ndarray]:
    """:func:`frame_flags` for the poses of ``trajectory`` (e.g. the subset paired with ground truth), by stamp."""
    stamps = np.array([s.stamp for s in stats])
    if not len(stamps):
        return {}
    order = np.argsort(stamps)
    position = np.clip(np.searchsorted(stamps[order], trajectory.stamps), 1, len(stamps) - 1)
    before, after = order[position - 1], order[position]
    nearest = np.where(np.abs(stamps[before] - trajectory.stamps) <= np.abs(stamps[after] - trajectory.stamps),
                       before, after)
    return {name: flags[nearest] for name, flags in frame_flags(stats, keyframes).items()}


def plot_run_trajectory(path: Path, trajectory: Trajectory, stats: list[FrameStats], title: str,
                        evaluation: dict | None = None, keyframes: set[int] | None = None) -> Path:
    """The trajectory with start, end, keyframes, masked and lost frames marked; against the aligned ground
    truth and with the ATE over time when ``evaluation`` (the arrays of ``twohr.evaluation.evaluate``) is given."""
    if evaluation is not None:
        est = evaluation["est"]
        return plot_trajectories(path, evaluation["gt"], est, evaluation["ate"], title=title,
                                 marks=flags_for(est, stats, keyframes))
    return plot_trajectory(path, trajectory, marks=flags_for(trajectory, stats, keyframes), title=title)


def plot_run_timeline(path: Path, stats: list[FrameStats], title: str, keyframes: set[int] | None = None) -> Path:
    """Keypoints, inliers, mask % and ms per stage, frame by frame; lost frames and keyframes shaded."""
    column = {name: np.array([getattr(s, name) for s in stats], float) for name in (
        "keypoints", "kept", "inliers", "mask_percent", "ms_detector", "ms_yolo", "ms_tracker", "ms_total")}
    flags = frame_flags(stats, keyframes)
    panels = {
        "features": {"keypoints": column["keypoints"], "kept / tracked": column["kept"],
                     "inliers": column["inliers"]},
        "mask %": {"dynamic mask": column["mask_percent"]},
        "ms": {"detector": column["ms_detector"], "yolo": column["ms_yolo"], "tracker": column["ms_tracker"],
               "total": column["ms_total"]},
    }
    index = np.array([s.index for s in stats])
    return plot_timeline(path, index, panels, spans={"keyframe": flags["keyframe"], "lost": flags["lost"]},
                         title=title)


def _row(name: str, value) -> str:
    return f"<tr><th>{html.escape(name)}</th><td>{html.escape(str(value))}</td></tr>"


def write_report_html(out: Path, name: str, summary: dict) -> Path:
    """``report.html`` in ``out``: the summary and links to every file of the run that exists."""
    rows = [_row("sequence", summary.get("sequence", name)), _row("frames", summary.get("frames")),
            _row("tracked", f"{summary.get('tracked_percent')} %"), _row("FPS", summary.get("fps")),
            _row("lost frames", len(summary.get("lost_frames", []))),
            _row("skipped (corrupt) frames", len(summary.get("skipped_frames", [])))]
    if "ate" in summary:
        rows += [_row("ATE RMSE (refined)", f"{summary['ate']['ate']['rmse']:.4f} m"),
                 _row("ATE RMSE (online)", f"{summary['ate_online']['ate']['rmse']:.4f} m"),
                 _row("RPE over 1 frame", f"{summary['ate']['rpe_frame']['rmse']:.4f} m"),
                 _row("RPE over 1 s", f"{summary['ate']['rpe_1s']['rmse']:.4f} m"),
                 _row("jitter (2nd difference of the error)", f"{summary['ate']['jitter']['rmse']:.4f} m")]
    for stage, ms in summary.get("ms_per_frame_median", {}).items():
        rows.append(_row(f"median {stage.removeprefix('ms_')} ms", ms))
    for key, value in summary.get("keyframe_jobs", {}).items():
        rows.append(_row(f"keyframe jobs: {key}", value))
    images = "".join(f'<figure><a href="{f}"><img src="{f}" alt="{f}"></a><figcaption>{caption}</figcaption></figure>'
                     for f, caption in (("trajectory.png", "trajectory: start, end, keyframes, masked and lost frames"),
                                        ("timeline.png", "per frame: keypoints, inliers, mask %, ms per stage"))
                     if (out / f).is_file())
    files = "".join(f'<li><a href="{f}">{f}</a> {html.escape(what)}</li>' for f, what in (
        ("stats.csv", "per-frame stats"), ("summary.json", "summary"), ("config.yaml", "the configuration"),
        ("trajectory.txt", "TUM, refined by bundle adjustment"), ("trajectory_online.txt", "TUM, as published live"))
        if (out / f).is_file())
    page = f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>twohr run: {html.escape(name)}</title>
<style>body{{font:14px/1.4 system-ui,sans-serif;margin:1.5rem;color:#1d2330}} table{{border-collapse:collapse}}
th,td{{text-align:left;padding:.2rem .8rem;border-bottom:1px solid #e4e7ec}} img{{max-width:100%}}
figure{{margin:1rem 0}}</style></head>
<body><h1>twohr run: {html.escape(name)}</h1>
<table>{"".join(rows)}</table>
{images}
<h2>Files</h2><ul>{files}</ul>
<details><summary>summary.json</summary><pre>{html.escape(json.dumps(summary, indent=2))}</pre></details>
</body></html>
"""
    path = out / "report.html"
    path.write_text(page)
    return path
