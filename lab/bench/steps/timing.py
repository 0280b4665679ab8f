"""Timed runs of the pipeline in this process: FPS, per-stage latency and memory, each run paired with a baseline
measured at the same time (this machine is shared), and ORB-SLAM3 beside them where it is installed."""

from __future__ import annotations

import platform
from dataclasses import dataclass, field

import numpy as np

from twohr.config import PipelineConfig, load_config
from twohr.machine import machine
from twohr_app.pipeline import run_sequence

from .figures import ate_rmse, peak_rss_mib, percentiles
from .orbslam3 import SideBySide


@dataclass
class RunFigures:
    """What the timed runs of our pipeline add up to: FPS and ATE per run, per-stage and per-frame latency, the
    keyframe jobs, and what the first run chose at warm-up (``detector.model=auto``: the network and its timings)."""

    fps: list[float] = field(default_factory=list)
    ate: list[float] = field(default_factory=list)
    stage_ms: dict[str, list[float]] = field(default_factory=lambda: {
        "ms_detector": [], "ms_yolo": [], "ms_tracker": [], "ms_total": []})
    latency: dict[str, list[float]] = field(default_factory=lambda: {"keyframe_frames": [], "other_frames": []})
    keyframe_ms: dict[str, list[float]] = field(default_factory=lambda: {
        "ms_detector": [], "ms_yolo": [], "ms_mapping": [], "ms_job": [], "lag_frames": []})
    chosen: dict = field(default_factory=dict)

    def add(self, run, sequence) -> None:
        self.fps.append(len(run.stats) / run.wall_s)
        self.chosen = self.chosen or run.chosen
        if (ate := ate_rmse(sequence, run.trajectory)) is not None:
            self.ate.append(ate)
        for key in self.stage_ms:
            self.stage_ms[key] += [getattr(s, key) for s in run.stats]
        for s in run.stats:
            self.latency["keyframe_frames" if s.keyframe else "other_frames"].append(s.ms_total)
        for job in run.keyframe_log:
            for key in self.keyframe_ms:
                self.keyframe_ms[key].append(getattr(job, key))


def throughput(sequence, config: PipelineConfig, frames: int = 60, start: int = 0, runs: int = 3,
               baseline: PipelineConfig | None = None, progress: bool = True) -> dict:
    """Run the pipeline ``runs`` times over the same frames; each run is paired with a run of ``baseline``
    (default: the ORB ablation) so that the ratio survives a noisy machine."""
    baseline = baseline or load_config(preset="orb")
    stop = min(len(sequence), start + frames)
    ours, baseline_fps = RunFigures(), []
    orbslam3 = SideBySide.if_installed(sequence, start, stop)
    for _ in range(runs):
        ours.add(run_sequence(sequence, config, start=start, stop=stop, progress=progress), sequence)
        run = run_sequence(sequence, baseline, start=start, stop=stop, progress=progress)
        baseline_fps.append(len(run.stats) / run.wall_s)
        if orbslam3 is not None:
            orbslam3.run_once(config, progress)
    fps, base = float(np.median(ours.fps)), float(np.median(baseline_fps))
    pipeline_rss = orbslam3.pipeline_rss if orbslam3 is not None else None
    return {**(orbslam3.comparison(fps) if orbslam3 is not None else SideBySide.not_run()),
            "ate_rmse_runs": [round(a, 4) for a in ours.ate],
            "ate_rmse_median": round(float(np.median(ours.ate)), 4) if ours.ate else None,
            "sequence": sequence.name, "frames": stop - start, "runs": runs,
            "fps_median": round(fps, 3), "fps_runs": [round(f, 3) for f in ours.fps],
            "baseline_fps_median": round(base, 3), "baseline": "ORB + mutual NN on the same tracker",
            "speed_ratio_to_baseline": round(fps / base, 4),
            "stages_ms": {k.removeprefix("ms_"): percentiles(v) for k, v in ours.stage_ms.items()},
            "per_frame_latency_ms": {k: percentiles(v) for k, v in ours.latency.items() if v},
            "keyframe_jobs": {k.removeprefix("ms_"): percentiles(v) for k, v in ours.keyframe_ms.items() if v},
            "mode": config.pipeline.mode, "chosen": ours.chosen,
            "peak_rss_mib": round(pipeline_rss or peak_rss_mib(), 1),
            **({"peak_rss_mib_with_orbslam3": round(peak_rss_mib(), 1)} if pipeline_rss else {}),
            "machine": {**machine(), "platform": platform.platform()}}
