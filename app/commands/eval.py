"""``twohr eval``: ATE and RPE of a trajectory (TUM text or a session's MCAP) against ground truth, as evo computes
them."""

from __future__ import annotations

import argparse
from pathlib import Path

from twohr.errors import TwohrError


def _eval(args: argparse.Namespace) -> int:
    from twohr.dataset import load_gt_extrinsic
    from twohr.evaluation import evaluate
    from twohr.trajectory import read_tum

    from ..plots import plot_trajectories

    name, left, right = load_gt_extrinsic(args.gt_extrinsic)
    gt = read_tum(args.gt).transformed(left, right)
    if Path(args.est).suffix == ".mcap":
        from twohr_services.recorder.core import recorded_trajectory

        est = recorded_trajectory(args.est, args.robot)
    else:
        est = read_tum(args.est)
    try:
        report, arrays = evaluate(gt, est, align=args.align, max_dt=args.max_dt, gt_extrinsic=name)
    except ValueError as exc:
        raise TwohrError(str(exc)) from None
    print(format_report(report))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(report.model_dump_json(indent=2))
        print(f"report: {args.json}")
    if args.plot:
        plot_trajectories(args.plot, arrays["gt"], arrays["est"], arrays["ate"],
                          title=f"{Path(args.est).name} vs {Path(args.gt).name}")
        print(f"plot:   {args.plot}")
    return 0


def format_report(report) -> str:
    """A short human-readable block for an :class:`~twohr.evaluation.EvaluationReport`."""
    a, r1, rs = report.ate, report.rpe_frame, report.rpe_1s
    return "\n".join([
        f"ATE ({report.align}, max dt {report.max_dt} s, gt extrinsic {report.gt_extrinsic}): "
        f"RMSE {a.rmse:.4f} m  mean {a.mean:.4f}  median {a.median:.4f}  std {a.std:.4f}  max {a.max:.4f}",
        f"RPE trans: per frame RMSE {r1.rmse:.4f} m, over 1 s RMSE {rs.rmse:.4f} m"
        + (f"; jitter RMSE {report.jitter.rmse:.4f} m" if report.jitter is not None else "")
        + (f"; Sim(3) scale {report.sim3_scale:.4f}" if report.sim3_scale is not None else ""),
        f"paired {report.matched} of {report.estimate_poses} estimate poses; GT coverage {report.gt_coverage:.1f} %"
        + (f"; scale {report.scale:.4f}" if report.align == "sim3" else ""),
    ])


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("eval", help="ATE/RPE of a trajectory against ground truth (TUM/evo conventions)",
                       description="ATE after Umeyama alignment and translational RPE, as evo_ape/evo_rpe "
                       "compute them. Trajectories are TUM text files; --est may also be a session recording "
                       "(.mcap), whose poses are scored.")
    p.add_argument("--gt", required=True, help="ground-truth trajectory (TUM format)")
    p.add_argument("--est", required=True, help="estimated trajectory (TUM format, or a twohr .mcap recording)")
    p.add_argument("--robot", default=None, help="with an .mcap holding several robots: whose poses to score")
    p.add_argument("--align", choices=["se3", "sim3", "none"], default="se3", help="alignment (default se3)")
    p.add_argument("--max-dt", type=float, default=0.02, help="association window in seconds (default 0.02)")
    p.add_argument("--gt-extrinsic", default="none",
                   help="fixed sensor extrinsic for the ground truth: none, bonn, or a 4x4 matrix file")
    p.add_argument("--json", help="write the report as JSON here")
    p.add_argument("--plot", help="write a PNG with top/side views and ATE over time here")
    p.set_defaults(func=_eval)
