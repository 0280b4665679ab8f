"""Trajectory accuracy as the field measures it: ATE after Umeyama alignment and RPE.

The association, alignment and statistics follow the TUM RGB-D tools and evo
(``evo_ape tum GT EST -a --t_max_diff 0.02``): each pose of the shorter trajectory is
paired with the nearest-in-time pose of the longer one within ``max_dt`` seconds.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, Field

from .config import SAME_PLACE_DEG, SAME_PLACE_M
from .geometry import invert_pose, make_pose, umeyama
from .pose import pose_difference
from .trajectory import Trajectory, interpolate_poses


class ErrorStats(BaseModel):
    """Summary statistics of a per-pose error, in metres."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    count: int

    @classmethod
    def of(cls, errors: np.ndarray) -> ErrorStats:
        e = np.asarray(errors, dtype=np.float64)
        if e.size == 0:
            nan = float("nan")
            return cls(rmse=nan, mean=nan, median=nan, std=nan, min=nan, max=nan, count=0)
        return cls(
            rmse=float(np.sqrt(np.mean(e**2))),
            mean=float(e.mean()),
            median=float(np.median(e)),
            std=float(e.std()),
            min=float(e.min()),
            max=float(e.max()),
            count=int(e.size),
        )


class EvaluationReport(BaseModel):
    """Everything ``twohr eval`` reports for one estimate against one ground truth."""

    align: str = Field(description="se3, sim3 or none")
    max_dt: float = Field(description="association window in seconds")
    gt_extrinsic: str = Field(description="fixed sensor extrinsic applied to the ground truth")
    matched: int = Field(description="estimate poses paired with a ground-truth pose")
    estimate_poses: int
    gt_coverage: float = Field(description="% of ground-truth poses within the estimate's time span that were paired")
    scale: float
    ate: ErrorStats
    rpe_frame: ErrorStats = Field(description="translational RPE between consecutive paired poses")
    rpe_1s: ErrorStats = Field(description="translational RPE over 1 second")
    jitter: ErrorStats | None = Field(None, description="norm of the second difference of the aligned position "
                                      "error over consecutive paired poses: zero for any smooth drift, large for "
                                      "frame-to-frame zig-zag")
    sim3_scale: float | None = Field(None, description="scale of a Sim(3) Umeyama alignment of the estimate onto "
                                     "the ground truth (> 1: the estimate's translations come out short)")


def associate(stamps_a: np.ndarray, stamps_b: np.ndarray, max_dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices (ia, ib) pairing each stamp of ``a`` with the nearest stamp of sorted ``b`` within ``max_dt``.

    Ties go to the earlier stamp of ``b``, as in evo's ``matching_time_indices``.
    """
    stamps_a = np.asarray(stamps_a, dtype=np.float64)
    stamps_b = np.asarray(stamps_b, dtype=np.float64)
    if len(stamps_a) == 0 or len(stamps_b) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    upper = np.clip(np.searchsorted(stamps_b, stamps_a, side="right"), 0, len(stamps_b) - 1)
    diff_ub = stamps_b[upper] - stamps_a
    lower = upper - 1
    diff_lb = np.where(lower >= 0, stamps_a - stamps_b[np.maximum(lower, 0)], np.inf)
    take_upper = (diff_ub <= max_dt) & (diff_ub < diff_lb)
    take_lower = ~take_upper & (diff_lb <= max_dt) & (diff_lb <= diff_ub)
    ia = np.flatnonzero(take_upper | take_lower)
    ib = np.where(take_upper, upper, lower)[ia]
    return ia, ib


def associate_trajectories(gt: Trajectory, est: Trajectory, max_dt: float) -> tuple[Trajectory, Trajectory]:
    """Paired copies of ``gt`` and ``est``; the shorter one is the reference, as in evo."""
    if len(est) <= len(gt):
        ie, ig = associate(est.stamps, gt.stamps, max_dt)
    else:
        ig, ie = associate(gt.stamps, est.stamps, max_dt)
    return gt.subset(ig), est.subset(ie)


def align_trajectory(est: Trajectory, gt: Trajectory, mode: str = "se3") -> tuple[Trajectory, float]:
    """``est`` moved onto ``gt`` by Umeyama alignment of positions (``se3``, ``sim3`` or ``none``)."""
    if mode == "none":
        return est, 1.0
    if mode not in ("se3", "sim3"):
        raise ValueError(f"unknown alignment {mode!r}; use se3, sim3 or none")
    if np.ptp(est.positions, axis=0).max() < 1e-12:
        # a camera that never moved: rotation is undetermined, so align by translation only
        rotation, translation, scale = np.eye(3), gt.positions.mean(0) - est.positions[0], 1.0
    else:
        rotation, translation, scale = umeyama(est.positions, gt.positions, with_scale=mode == "sim3")
    poses = est.poses.copy()
    poses[:, :3, :3] = np.einsum("ij,njk->nik", rotation, poses[:, :3, :3])
    poses[:, :3, 3] = scale * est.positions @ rotation.T + translation
    return Trajectory(est.stamps.copy(), poses), scale


def ate_errors(gt: Trajectory, est_aligned: Trajectory) -> np.ndarray:
    """Per-pose translational absolute trajectory error of paired, aligned trajectories."""
    return np.linalg.norm(gt.positions - est_aligned.positions, axis=1)


def rpe_errors(gt: Trajectory, est: Trajectory, delta_s: float | None = None) -> np.ndarray:
    """Translational relative pose error of paired trajectories.

    With ``delta_s`` None the pairs are consecutive poses; otherwise each pose is paired
    with the first pose at least ``delta_s`` seconds later.
    """
    n = len(gt)
    if n < 2:
        return np.zeros(0)
    if delta_s is None:
        i = np.arange(n - 1)
        j = i + 1
    else:
        j = np.searchsorted(gt.stamps, gt.stamps + delta_s - 1e-9, side="left")
        i = np.flatnonzero(j < n)
        j = j[i]
    rel_gt = invert_pose(gt.poses[i]) @ gt.poses[j]
    rel_est = invert_pose(est.poses[i]) @ est.poses[j]
    err = invert_pose(rel_gt) @ rel_est
    return np.linalg.norm(err[:, :3, 3], axis=1)


def jitter_errors(gt: Trajectory, est_aligned: Trajectory) -> np.ndarray:
    """Per-pose zig-zag of paired, aligned trajectories: ``|e[i-1] - 2 e[i] + e[i+1]|`` of the position error
    ``e``. A constant offset or a drift linear in the frame index gives 0; independent noise of sigma per axis
    gives about ``sqrt(6 * 3) * sigma`` RMS."""
    error = est_aligned.positions - gt.positions
    if len(error) < 3:
        return np.zeros(0)
    return np.linalg.norm(error[:-2] - 2 * error[1:-1] + error[2:], axis=1)


def evaluate(
    gt: Trajectory,
    est: Trajectory,
    *,
    align: str = "se3",
    max_dt: float = 0.02,
    gt_extrinsic: str = "none",
) -> tuple[EvaluationReport, dict[str, Trajectory | np.ndarray]]:
    """ATE, RPE and coverage of ``est`` against ``gt``; returns the report and arrays for plotting."""
    gt_paired, est_paired = associate_trajectories(gt, est, max_dt)
    if len(gt_paired) < 3:
        raise ValueError(
            f"only {len(gt_paired)} estimate poses have a ground-truth pose within {max_dt} s; "
            "check that both files use the same clock, or raise --max-dt"
        )
    est_aligned, scale = align_trajectory(est_paired, gt_paired, align)
    errors = ate_errors(gt_paired, est_aligned)
    in_span = (gt.stamps >= est.stamps[0] - max_dt) & (gt.stamps <= est.stamps[-1] + max_dt)
    covered = len(np.unique(associate(gt.stamps[in_span], est.stamps, max_dt)[0]))
    report = EvaluationReport(
        align=align,
        max_dt=max_dt,
        gt_extrinsic=gt_extrinsic,
        matched=len(gt_paired),
        estimate_poses=len(est),
        gt_coverage=100.0 * covered / max(1, int(in_span.sum())),
        scale=scale,
        ate=ErrorStats.of(errors),
        rpe_frame=ErrorStats.of(rpe_errors(gt_paired, est_aligned)),
        rpe_1s=ErrorStats.of(rpe_errors(gt_paired, est_aligned, delta_s=1.0)),
        jitter=ErrorStats.of(jitter_errors(gt_paired, est_aligned)),
        sim3_scale=scale if align == "sim3" else _sim3_scale(est_paired, gt_paired),
    )
    arrays = {"gt": gt_paired, "est": est_aligned, "ate": errors}
    return report, arrays


def _sim3_scale(est: Trajectory, gt: Trajectory) -> float | None:
    """The Sim(3) alignment's scale, None where the positions are degenerate (a line, a point)."""
    try:
        return align_trajectory(est, gt, "sim3")[1]
    except ValueError:
        return None


def static_trajectory(stamps: np.ndarray) -> Trajectory:
    """A camera that never moves: identity poses at the given stamps (a sanity baseline)."""
    return Trajectory(stamps, np.tile(make_pose(np.eye(3), np.zeros(3)), (len(stamps), 1, 1)))


def joint_ate(pairs: list[tuple[Trajectory, Trajectory]], max_dt: float = 0.02) -> tuple[float, list[float]]:
    """ATE RMSE of several robots' trajectories in one frame (a shared map's): each ``(ground truth, estimate)``
    associated on its own (``max_dt``), then one SE(3) Umeyama alignment over the pairs of all of them, so that a
    robot placed wrongly in the shared frame cannot be aligned away on its own. Returns the RMSE over all pairs and
    each robot's under that one alignment."""
    paired = [associate_trajectories(gt, est, max_dt) for gt, est in pairs]
    gt_all = np.concatenate([gt.positions for gt, _ in paired])
    est_all = np.concatenate([est.positions for _, est in paired])
    if len(gt_all) < 3:
        raise ValueError(f"only {len(gt_all)} estimate poses have a ground-truth pose within {max_dt} s")
    rotation, translation, _ = umeyama(est_all, gt_all)
    errors = [np.linalg.norm(gt.positions - (est.positions @ rotation.T + translation), axis=1) for gt, est in paired]
    rmse = float(np.sqrt(np.mean(np.concatenate(errors) ** 2)))
    return rmse, [float(np.sqrt(np.mean(e ** 2))) if len(e) else float("nan") for e in errors]


def loops_against_ground_truth(loops: list[dict], ground_truth: Trajectory) -> dict:
    """Each closed loop's two keyframes compared on the ground truth (``gt_distance_m``, ``gt_angle_deg`` added
    to its entry), and how many are false accepts (not the same place: ``SAME_PLACE_M``, ``SAME_PLACE_DEG``)."""
    false_accepts = 0
    for loop in loops:
        poses, valid = interpolate_poses(ground_truth, np.array([loop["stamp"], loop["candidate_stamp"]]))
        if not valid.all():
            continue
        metres, degrees = pose_difference(poses[0], poses[1])
        loop.update(gt_distance_m=round(metres, 3), gt_angle_deg=round(degrees, 2))
        false_accepts += metres > SAME_PLACE_M or degrees > SAME_PLACE_DEG
    return {"false_accepts": false_accepts}
