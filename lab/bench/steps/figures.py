"""Figures every timed study reports the same way: percentiles of timings, a run's ATE, this process's memory."""

from __future__ import annotations

import resource

import numpy as np

from twohr.evaluation import evaluate


def peak_rss_mib() -> float:
    """Peak resident memory of this process so far, MiB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def percentiles(values: list[float]) -> dict[str, float]:
    """Median, p90 and p99 of ``values``, rounded to 0.01."""
    arr = np.asarray(values, float)
    return {"median": round(float(np.median(arr)), 2), "p90": round(float(np.percentile(arr, 90)), 2),
            "p99": round(float(np.percentile(arr, 99)), 2)}


def ate_rmse(sequence, trajectory) -> float | None:
    """ATE RMSE of ``trajectory`` against the sequence's ground truth (camera frame, SE(3) Umeyama); None without
    ground truth or with fewer than 3 poses."""
    if not sequence.has_ground_truth() or len(trajectory) < 3:
        return None
    extrinsic = sequence.default_gt_extrinsic()
    return evaluate(sequence.ground_truth(extrinsic), trajectory, gt_extrinsic=extrinsic)[0].ate.rmse
