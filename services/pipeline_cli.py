"""``twohr demo``: the main job end to end on one sequence, with a printed result.

Until the full pipeline lands, the demo runs what exists (dataset loading, model
verification, evaluation of the static-camera baseline) and says what is missing.
"""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path


def _demo(args: argparse.Namespace) -> int:
    from twohr import models
    from twohr.dataset import RGBDSequence
    from twohr.evaluation import evaluate, static_trajectory
    from twohr.trajectory import write_tum

    from .cli import format_report

    seq = RGBDSequence(args.sequence)
    print(f"sequence {seq.name}: {len(seq)} RGB-D frames, camera fx={seq.camera.fx:.1f} fy={seq.camera.fy:.1f}")
    for name in ("faster2d2_WASF_N16", "yolov8n_320"):
        print(f"model {name}: {models.model_path(name)}")
    out = Path(args.out)
    if importlib.util.find_spec("twohr_services.tracker.core") is None:
        print("MISSING: the tracker core (issue: tracker core and `twohr run`); showing the static-camera baseline")
        est = static_trajectory(seq.stamps)
        write_tum(out / "static_baseline.txt", est)
        gt = seq.ground_truth(seq.default_gt_extrinsic())
        report, _ = evaluate(gt, est, max_dt=0.02, gt_extrinsic=seq.default_gt_extrinsic())
        print("static camera baseline:")
        print(format_report(report))
        return 0
    raise NotImplementedError("the tracker core exists but the demo does not run it yet")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="run the main job on one sequence and print the result")
    p.add_argument("--sequence", default="../shared/data/rgbd_bonn_crowd_dev", help="TUM-layout RGB-D folder")
    p.add_argument("--out", default="runs/demo", help="output folder")
    p.set_defaults(func=_demo)
