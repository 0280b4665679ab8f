"""``twohr bench --ablations`` (``twohr bench ablations``): ATE RMSE, S.D., % tracked and ms/frame of ORB, R2D2, 2HR,
2HR+YOLO and the full pipeline (the named presets) on the same tracker, and a static camera as the sanity row, over
``--frames`` frames (default: all). ablations.md; bench.json: ``ablations``."""

from __future__ import annotations

import argparse

from .common import report_table

NAME = "ablations"
HELP = "the ablation table: ATE, S.D., frames tracked and ms/frame of each preset on the same tracker"


def add_arguments(p: argparse.ArgumentParser, legacy: bool = False) -> None:
    if legacy:
        p.add_argument("--ablations", action="store_true", help="the ablation table instead of throughput")


def picked(args: argparse.Namespace) -> bool:
    return args.ablations


def run(args: argparse.Namespace, config, sequence, out) -> dict:
    from .steps.ablation_runs import ablations, format_table, static_camera_row

    rows = ablations(sequence, config, stop=args.frames, progress=not args.quiet)
    rows.append(static_camera_row(sequence))
    report_table(out, "ablations", format_table(rows), args.argv)
    return {"ablations": {"sequence": sequence.name, "frames": args.frames or len(sequence),
                          "ate": "RMSE after SE(3) Umeyama alignment, max dt 0.02 s, camera-frame GT", "rows": rows}}
