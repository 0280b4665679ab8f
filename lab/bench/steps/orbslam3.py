"""ORB-SLAM3 RGB-D (pyorbslam3, GPL-3.0, optional) on the same frames: the side-by-side of ``twohr bench``."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from twohr.evaluation import evaluate
from twohr.models import REPO_ROOT
from twohr.trajectory import Trajectory
from twohr_app.pipeline import run_sequence

from .figures import ate_rmse, peak_rss_mib, percentiles
from .frames import FramesInMemory, frames_fit_in_memory

#: Where ORB-SLAM3's vocabulary and settings for the dev camera live (``../shared/baselines`` beside the repo);
#: override with $PYORBSLAM3_VOCAB and $TWOHR_ORBSLAM3_SETTINGS.
BASELINES_DIR = REPO_ROOT.parent / "shared" / "baselines"


def orbslam3_files() -> tuple[Path, Path] | None:
    """(vocabulary, settings) for ORB-SLAM3 RGB-D, or None when pyorbslam3 or the files are missing."""
    try:
        import pyorbslam3  # noqa: F401  (GPL-3.0, an optional benchmark comparison, not a dependency)
    except ImportError:
        return None
    vocab = Path(os.environ.get("PYORBSLAM3_VOCAB", BASELINES_DIR / "ORBvoc_generic_nobonn_k10L6.txt"))
    settings = Path(os.environ.get("TWOHR_ORBSLAM3_SETTINGS", BASELINES_DIR / "orbslam3_bonn_rgbd.yaml"))
    return (vocab, settings) if vocab.is_file() and settings.is_file() else None


def orbslam3_run(sequence, start: int, stop: int, files: tuple[Path, Path]) -> dict:
    """ORB-SLAM3 RGB-D (pyorbslam3) on the same frames: ms per ``track_rgbd`` call (median and mean) and its
    trajectory's ATE. Frames are read before timing; only the tracking calls are timed, as ORB-SLAM3's own
    examples do."""
    import pyorbslam3

    slam = pyorbslam3.Slam(str(files[0]), str(files[1]), pyorbslam3.Sensor.RGBD)
    stamps, poses, ms = [], [], []
    try:
        for frame in sequence.frames(start, stop):
            raw_depth = (frame.depth * sequence.camera.depth_factor).astype(np.float32)
            t0 = time.perf_counter()
            result = slam.track_rgbd(frame.rgb, raw_depth, frame.stamp)
            ms.append((time.perf_counter() - t0) * 1000)
            if result.pose_valid:
                stamps.append(frame.stamp)
                poses.append(np.asarray(result.pose_wc, np.float64))
    finally:
        slam.shutdown()
    out = {"ms_per_frame": {**percentiles(ms), "mean": round(float(np.mean(ms)), 2)},
           "tracked_percent": round(100 * len(poses) / max(1, len(ms)), 1)}
    if sequence.has_ground_truth() and len(poses) >= 3:
        extrinsic = sequence.default_gt_extrinsic()
        report, _ = evaluate(sequence.ground_truth(extrinsic), Trajectory(np.array(stamps), np.array(poses)),
                             gt_extrinsic=extrinsic)
        out["ate_rmse"] = round(report.ate.rmse, 4)
    return out


def like_for_like(ours_ms: list[float], ours_ate: list[float], orbslam3_mean_ms: float) -> dict:
    """The like-for-like comparison's figures: our wall ms per frame and ATE per run, over frames held in memory,
    against ORB-SLAM3's mean ``track_rgbd`` ms on the same frames."""
    ours = float(np.median(ours_ms))
    return {"ours_ms_per_frame": round(ours, 2), "ours_runs": [round(m, 2) for m in ours_ms],
            "ours_ate_rmse_runs": [round(a, 4) for a in ours_ate],
            "ours_ate_rmse_median": round(float(np.median(ours_ate)), 4) if ours_ate else None,
            "orbslam3_ms_per_frame": round(orbslam3_mean_ms, 2),
            "ratio_ms_per_frame": round(ours / orbslam3_mean_ms, 3),
            "note": "both on the same frames decoded before the clock, both a mean over every frame: ours the run's "
                    "wall time per frame (waiting for its last keyframe jobs), ORB-SLAM3 the mean of its track_rgbd "
                    "calls (its local mapping runs on beside them)"}


#: what the throughput study reports where ORB-SLAM3 could not run
NOT_RUN = "not run: pip install pyorbslam3 and put its vocabulary and settings in ../shared/baselines (or set " \
    "PYORBSLAM3_VOCAB)"


class SideBySide:
    """ORB-SLAM3 beside our timed runs: once per run, ORB-SLAM3 on the same frames and (where they fit in memory)
    ours again on frames decoded before the clock, for the like-for-like ratio. Our peak memory is taken before the
    first of these runs: the frames held and ORB-SLAM3 in this process come after it."""

    def __init__(self, sequence, start: int, stop: int, files: tuple[Path, Path]) -> None:
        self.sequence, self.start, self.stop, self.files = sequence, start, stop, files
        self.fits, self.why_not = frames_fit_in_memory(sequence, start, stop)
        self.in_memory: FramesInMemory | None = None
        self.pipeline_rss: float | None = None
        self.runs: list[dict] = []
        self.ours_ms: list[float] = []  # ours, wall ms per frame with the frames decoded before the clock
        self.ours_ate: list[float] = []

    @classmethod
    def if_installed(cls, sequence, start: int, stop: int) -> SideBySide | None:
        files = orbslam3_files()
        return None if files is None else cls(sequence, start, stop, files)

    def run_once(self, config, progress: bool) -> None:
        if self.pipeline_rss is None:
            self.pipeline_rss = peak_rss_mib()
            self.in_memory = FramesInMemory(self.sequence, self.start, self.stop) if self.fits else None
        if self.in_memory is not None:
            run = run_sequence(self.in_memory, config, start=self.start, stop=self.stop, progress=progress)
            self.ours_ms.append(1000 * run.wall_s / max(1, len(run.stats)))
            if (ate := ate_rmse(self.sequence, run.trajectory)) is not None:
                self.ours_ate.append(ate)
        frames = self.sequence if self.in_memory is None else self.in_memory
        self.runs.append(orbslam3_run(frames, self.start, self.stop, self.files))

    @staticmethod
    def not_run() -> dict:
        return {"orbslam3": NOT_RUN}

    def comparison(self, fps: float) -> dict:
        """``{"orbslam3": …}`` of the throughput study against our median ``fps``."""
        if not self.runs:
            return self.not_run()
        orb_ms = float(np.median([r["ms_per_frame"]["median"] for r in self.runs]))
        orb_mean_ms = float(np.median([r["ms_per_frame"]["mean"] for r in self.runs]))
        return {"orbslam3": {
            "ms_per_frame_median": round(orb_ms, 2), "runs": self.runs,
            "ratio_ms_per_frame": round((1000 / fps) / orb_ms, 3),
            "note": "ours: wall time per frame over the whole run, the frames read and decoded during it; "
                    "ORB-SLAM3: the median of its track_rgbd calls on frames read before",
            "like_for_like": like_for_like(self.ours_ms, self.ours_ate, orb_mean_ms) if self.ours_ms else
            {"not_run": self.why_not}}}
