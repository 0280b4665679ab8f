"""Which keyframe translations do the images agree with? A ground-truth-free check of a run::

    .venv/bin/twohr run --sequence ../shared/data/rgbd_bonn_crowd_dev --out runs/dev --set pipeline.synchronous=true
    .venv/bin/python -m twohr_lab.tracking.consistency --run runs/dev --out runs/consistency

Feature tracks are built over the run's keyframes independently of the pipeline (SIFT, ratio test, a
fundamental-matrix RANSAC per pair, pairs up to ``--max-gap`` keyframes apart joined into tracks; people masked by
YOLO). Then, for each candidate trajectory, every keyframe's camera *centre* is held at the candidate's while the
rotations and the 3-D points settle. The cost is the one the tracker's bundle adjustment minimises (the residuals of
``twohr.pose.observation_residuals``: pixels and the inverse-depth residual with ``--depth-noise``
as ``tracker.depth_noise``; Huber loss at ``--huber`` px), and so is the solver (Levenberg-Marquardt with the points
eliminated by the same Schur complement). The cost that remains says how well the candidate's translations explain
the observations.

Candidates: the run's refined trajectory, the ground truth (SE(3)-aligned to it) and three controls that move the
estimate by exactly as much as the ground truth does, in other directions (the difference reversed in time, its
axes permuted, negated). A cost near the estimate's for the ground truth, far below the controls', means the
estimate's error lies along a direction the data hardly constrains. The fits crawl (the controls take hundreds of
iterations; 136 keyframes, 2000 at most, run in about 10 minutes), so the defaults run to a relative step of 1e-9 and
the table says whether each fit converged. Writes ``consistency.md`` and ``consistency.json`` into ``--out``.
"""

from __future__ import annotations

import argparse
import csv
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from twohr.config import TrackerConfig
from twohr.errors import TwohrError
from twohr.geometry import depth_at_pixels, huber_loss, huber_weights, skew, so3_exp_batch, umeyama
from twohr.pose import observation_residuals
from twohr.trajectory import interpolate_poses, read_tum
from twohr_services.tracker.bundle_adjustment import normal_equations, schur_layout, solve_schur

from ..stamp import write_study
from .sensitivity import DEFAULT_SEQUENCE

#: The tracker's defaults: the fit scores what its bundle adjustment minimises.
DEFAULT_DEPTH_NOISE = TrackerConfig.model_fields["depth_noise"].default
DEFAULT_HUBER_PX = TrackerConfig.model_fields["huber_px"].default


@dataclass
class Tracks:
    """Observations of 3-D points: observation ``o`` sees point ``point[o]`` from keyframe ``frame[o]`` at ``xy[o]``
    with measured depth ``depth[o]`` (metres, 0 = none)."""

    frame: np.ndarray
    point: np.ndarray
    xy: np.ndarray
    depth: np.ndarray

    @property
    def num_points(self) -> int:
        return int(self.point.max()) + 1 if len(self.point) else 0


@dataclass
class Fit:
    """What remains after the rotations and points have settled under fixed camera centres."""

    cost_reprojection: float
    cost_depth: float
    median_px: float
    poses: np.ndarray
    converged: bool

    @property
    def cost(self) -> float:
        return self.cost_reprojection + self.cost_depth


def build_tracks(grays: list[np.ndarray], depths: list[np.ndarray], masks: list[np.ndarray | None],
                 max_gap: int = 8, ratio: float = 0.75, min_length: int = 3) -> Tracks:
    """SIFT tracks over ordered images: matches between images at most ``max_gap`` apart (ratio test, then a
    fundamental-matrix RANSAC at 1 px) joined into tracks; a track is kept when it has ``min_length``
    observations and at most one per image. ``masks`` (True = ignore) keep features off moving objects."""
    sift = cv2.SIFT_create(1500)
    features = []
    for gray, mask in zip(grays, masks, strict=True):
        keep = None if mask is None else (~mask).astype(np.uint8) * 255
        keypoints, descriptors = sift.detectAndCompute(gray, keep)
        features.append((np.array([k.pt for k in keypoints], np.float64).reshape(-1, 2), descriptors))
    offsets = np.cumsum([0] + [len(xy) for xy, _ in features])
    parent = np.arange(offsets[-1])

    def root(node: int) -> int:
        while parent[node] != node:
            parent[node] = parent[parent[node]]
            node = parent[node]
        return node

    matcher = cv2.BFMatcher(cv2.NORM_L2)
    for i in range(len(features)):
        for j in range(i + 1, min(len(features), i + max_gap + 1)):
            (xy_i, desc_i), (xy_j, desc_j) = features[i], features[j]
            if desc_i is None or desc_j is None or len(desc_i) < 2 or len(desc_j) < 2:
                continue
            good = [m for m, n in matcher.knnMatch(desc_i, desc_j, k=2) if m.distance < ratio * n.distance]
            if len(good) < 20:
                continue
            a = np.array([m.queryIdx for m in good])
            b = np.array([m.trainIdx for m in good])
            _, inliers = cv2.findFundamentalMat(xy_i[a], xy_j[b], cv2.FM_RANSAC, 1.0, 0.999)
            if inliers is None:
                continue
            for qa, qb in zip(a[inliers.ravel() > 0], b[inliers.ravel() > 0], strict=True):
                parent[root(offsets[i] + qa)] = root(offsets[j] + qb)
    roots = np.array([root(n) for n in range(offsets[-1])])
    node_frame = np.repeat(np.arange(len(features)), np.diff(offsets))
    order = np.argsort(roots, kind="stable")
    groups = np.split(order, np.flatnonzero(np.diff(roots[order])) + 1)
    frame, point, xy = [], [], []
    for nodes in groups:
        frames = node_frame[nodes]
        if len(nodes) < min_length or len(np.unique(frames)) != len(frames):
            continue
        point_id = point[-1] + 1 if point else 0
        for node, f in zip(nodes, frames, strict=True):
            frame.append(f)
            point.append(point_id)
            xy.append(features[f][0][node - offsets[f]])
    frame, xy = np.array(frame, int), np.array(xy, np.float64).reshape(-1, 2)
    depth = np.zeros(len(frame))
    for f in np.unique(frame):
        seen = frame == f
        depth[seen] = np.nan_to_num(depth_at_pixels(depths[f], xy[seen], 0.3, 6.0), nan=0.0)
    return Tracks(frame, np.array(point, int), xy, depth)


def initial_points(tracks: Tracks, poses: np.ndarray, k: np.ndarray) -> tuple[Tracks, np.ndarray]:
    """World points (M, 3) back-projected from each track's first observation with depth, through ``poses``
    (camera-to-world); tracks without any depth are dropped (and the rest renumbered)."""
    with_depth = np.flatnonzero(tracks.depth > 0)
    seeds = with_depth[np.unique(tracks.point[with_depth], return_index=True)[1]]
    kept = np.zeros(tracks.num_points, bool)
    kept[tracks.point[seeds]] = True
    renumber = np.cumsum(kept) - 1
    keep_obs = kept[tracks.point]
    kept_tracks = Tracks(tracks.frame[keep_obs], renumber[tracks.point[keep_obs]], tracks.xy[keep_obs],
                         tracks.depth[keep_obs])
    z = tracks.depth[seeds]
    rays = np.c_[(tracks.xy[seeds] - k[:2, 2]) / np.diag(k)[:2], np.ones(len(seeds))]
    cam = poses[tracks.frame[seeds]]
    points = np.einsum("nij,nj->ni", cam[:, :3, :3], rays * z[:, None]) + cam[:, :3, 3]
    return kept_tracks, points


def fit_rotations(k: np.ndarray, poses: np.ndarray, tracks: Tracks, depth_noise: float = DEFAULT_DEPTH_NOISE,
                  iterations: int = 2000, tolerance: float = 1e-9, huber: float = DEFAULT_HUBER_PX) -> Fit:
    """Hold every camera centre of ``poses`` (camera-to-world) and let the rotations and points settle.

    Residuals per observation are the bundle adjustment's (``observation_residuals``: the pixel error (x, y) and,
    with measured depth, ``(1/z_pred - 1/z) / depth_noise``); Huber loss at ``huber``. Levenberg-Marquardt with the
    points eliminated by the bundle adjustment's Schur complement (``normal_equations``, ``solve_schur``); rotations
    are perturbed on the left, R <- exp(w) R, and the first rotation fixes the gauge. Converged when a step lowers
    the cost by less than ``tolerance`` (relative)."""
    tracks, points = initial_points(tracks, poses, k)
    rotations = poses[:, :3, :3].copy()
    centres = poses[:, :3, 3]
    n_frames = len(poses)
    slot = np.arange(n_frames) - 1  # frame 0 has no slot: it is fixed
    layout = schur_layout(slot[tracks.frame], tracks.point, n_frames - 1, tracks.num_points)

    def residuals(rotations: np.ndarray, points: np.ndarray):
        offset = points[tracks.point] - centres[tracks.frame]
        cam = np.einsum("nji,nj->ni", rotations[tracks.frame], offset)
        res, jac_cam = observation_residuals(k, cam, tracks.xy, tracks.depth, depth_noise)
        return res, jac_cam, offset

    res, jac_cam, offset = residuals(rotations, points)
    cost = float(huber_loss(res, huber).sum())
    damping = 1e-3
    converged = False
    for _ in range(iterations):
        # cam = R^T (X - c): d cam / d X = R^T; R <- exp(w) R gives d cam / d w = R^T skew(X - c).
        jac_point = jac_cam @ np.swapaxes(rotations[tracks.frame], 1, 2)
        jac_rotation = jac_point @ skew(offset)
        normal = normal_equations(layout, jac_rotation, jac_point, res, huber_weights(res, huber))
        for _attempt in range(8):
            steps = solve_schur(normal, damping)
            if steps is None:
                damping *= 10
                continue
            step_rotation, step_point = steps
            trial_rotations = rotations.copy()
            trial_rotations[1:] = so3_exp_batch(step_rotation) @ rotations[1:]
            trial_points = points + step_point
            trial_res, trial_jac, trial_offset = residuals(trial_rotations, trial_points)
            trial_cost = float(huber_loss(trial_res, huber).sum())
            if trial_cost < cost:
                converged = cost - trial_cost < tolerance * cost
                rotations, points, res, jac_cam, offset, cost = (trial_rotations, trial_points, trial_res, trial_jac,
                                                                 trial_offset, trial_cost)
                damping = max(damping / 3, 1e-7)
                break
            damping *= 5
        else:
            converged = True  # no step lowers the cost any more
        if converged:
            break
    fitted = poses.copy()
    fitted[:, :3, :3] = rotations
    costs = huber_loss(res, huber)
    return Fit(float(costs[:, :2].sum()), float(costs[:, 2].sum()), float(np.median(np.hypot(res[:, 0], res[:, 1]))),
               fitted, bool(converged))


def candidate_trajectories(estimate: np.ndarray, ground_truth: np.ndarray) -> dict[str, np.ndarray]:
    """The estimate, the ground truth SE(3)-aligned to it (with the estimate's rotations as a start) and three
    controls displaced from the estimate by the same amount as the ground truth, in other directions."""
    rotation, translation, _ = umeyama(ground_truth[:, :3, 3], estimate[:, :3, 3])
    aligned = estimate.copy()
    aligned[:, :3, 3] = ground_truth[:, :3, 3] @ rotation.T + translation
    difference = aligned[:, :3, 3] - estimate[:, :3, 3]
    reversed_in_time = difference[::-1] - difference[::-1].mean(0) + difference.mean(0)

    def displaced(by: np.ndarray) -> np.ndarray:
        poses = estimate.copy()
        poses[:, :3, 3] += by
        return poses

    return {"estimate": estimate, "ground truth": aligned,
            "control: difference reversed in time": displaced(reversed_in_time),
            "control: difference axes permuted": displaced(difference[:, [1, 2, 0]]),
            "control: difference negated": displaced(-difference)}


def load_keyframes(run: Path, sequence) -> tuple[list[int], np.ndarray, np.ndarray]:
    """The run's keyframe indices with ground truth, their refined poses and their camera-frame ground truth."""
    stats = run / "stats.csv"
    if not stats.is_file() or not (run / "trajectory.txt").is_file():
        raise TwohrError(f"{run} is not a run folder (stats.csv and trajectory.txt from `twohr run`)")
    with stats.open() as handle:
        indices = [int(row["index"]) for row in csv.DictReader(handle) if row["keyframe"] == "True"]
    stamps = sequence.stamps[indices]
    estimate, est_ok = interpolate_poses(read_tum(run / "trajectory.txt"), stamps)
    truth, gt_ok = interpolate_poses(sequence.ground_truth(sequence.default_gt_extrinsic()), stamps)
    keep = np.flatnonzero(est_ok & gt_ok)
    if len(keep) < 3:
        raise TwohrError(f"only {len(keep)} keyframes of {run} have both a pose and ground truth")
    return [indices[i] for i in keep], estimate[keep], truth[keep]


def format_table(rows: list[dict]) -> str:
    lines = ["| depth noise | candidate | cost | pixels | depth | median px | vs estimate | moved (mm RMS) "
             "| converged |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['depth_noise']:g} | {r['candidate']} | {r['cost']:.0f} | {r['cost_reprojection']:.0f} | "
                     f"{r['cost_depth']:.0f} | {r['median_px']:.3f} | {100 * r['relative']:+.2f} % | "
                     f"{r['moved_mm']:.1f} | {'yes' if r['converged'] else 'no'} |")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m twohr_lab.tracking.consistency", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", required=True, help="output folder of `twohr run` on --sequence")
    parser.add_argument("--sequence", default=DEFAULT_SEQUENCE, help="the run's TUM-layout RGB-D folder")
    parser.add_argument("--depth-noise", default=f"{DEFAULT_DEPTH_NOISE:g},1.0",
                        help="comma-separated inverse-depth sigmas (1/m) of the depth term, as tracker.depth_noise "
                             f"(default: the tracker's {DEFAULT_DEPTH_NOISE:g}, and 1.0, about pixels only)")
    parser.add_argument("--huber", type=float, default=DEFAULT_HUBER_PX,
                        help=f"Huber scale (px), as tracker.huber_px (default {DEFAULT_HUBER_PX:g})")
    parser.add_argument("--max-gap", type=int, default=8, help="match keyframes at most this many apart")
    parser.add_argument("--iterations", type=int, default=2000, help="Levenberg-Marquardt iterations at most")
    parser.add_argument("--out", default="runs/consistency", help="output folder (default runs/consistency)")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    program = "python -m twohr_lab.tracking.consistency"
    try:
        from twohr.dataset import RGBDSequence
        from twohr_services.yolo.masks import DynamicMasker

        noises = [float(v) for v in args.depth_noise.split(",") if v.strip()]
        if not noises or min(noises) <= 0:
            raise TwohrError(f"--depth-noise needs positive values, got {args.depth_noise!r}")
        if args.huber <= 0:
            raise TwohrError(f"--huber needs a positive value, got {args.huber!r}")
        sequence = RGBDSequence(args.sequence)
        indices, estimate, truth = load_keyframes(Path(args.run), sequence)
        masker = DynamicMasker()
        grays, depths, masks = [], [], []
        for i in indices:
            frame = sequence.read(i)
            masker.reset()
            masks.append(masker(frame.rgb, frame.depth).mask)
            grays.append(cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY))
            depths.append(frame.depth)
        tracks = build_tracks(grays, depths, masks, args.max_gap)
        print(f"{len(indices)} keyframes, {tracks.num_points} tracks, {len(tracks.frame)} observations", flush=True)
        k = sequence.camera.matrix
        rows = []
        for noise in noises:
            baseline = None
            for name, poses in candidate_trajectories(estimate, truth).items():
                fit = fit_rotations(k, poses, tracks, noise, args.iterations, huber=args.huber)
                baseline = fit.cost if baseline is None else baseline
                moved = np.sqrt(np.mean(np.sum((poses[:, :3, 3] - estimate[:, :3, 3]) ** 2, 1))) * 1000
                rows.append({"depth_noise": noise, "huber_px": args.huber, "candidate": name, "cost": fit.cost,
                             "cost_reprojection": fit.cost_reprojection, "cost_depth": fit.cost_depth,
                             "median_px": fit.median_px, "converged": fit.converged,
                             "relative": fit.cost / baseline - 1, "moved_mm": moved})
                print(format_table(rows[-1:]).splitlines()[-1], flush=True)
    except (TwohrError, ValueError) as exc:
        print(f"consistency: error: {exc}", file=sys.stderr)
        return 2
    table = format_table(rows)
    summary = (f"{len(indices)} keyframes, {tracks.num_points} SIFT tracks, {len(tracks.frame)} observations "
               f"(keyframes at most {args.max_gap} apart matched); Huber at {args.huber:g} px.")
    out = write_study(args.out, "consistency", f"{summary}\n\n{table}", rows, argv, program)
    print(table)
    print(f"written: {out / 'consistency.md'}, consistency.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
