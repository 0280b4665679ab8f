"""``twohr bench --share`` (``twohr bench share``): two live robots that track themselves build one map at once (map
mode ``share``), ``--runs`` times (:mod:`~twohr_lab.bench.steps.shared_map`): when and where the map server merges
the second, its cost, the bytes each way, the frames posed in the map's frame and the joint ATE. share.md;
bench.json: ``share`` (``rows``, ``joint_ate_median``, ``joint_ate_at_most_0_025``)."""

from __future__ import annotations

import argparse

from .common import report_table

NAME = "share"
HELP = "two live robots build one map at once (map mode share): the merge, its cost and the joint ATE"


def add_arguments(p: argparse.ArgumentParser, legacy: bool = False) -> None:
    if legacy:
        p.add_argument("--share", action="store_true", help="two live robots that track themselves build one map "
                       "at once (map mode share): when and where the map server merges the second, its cost, the "
                       "bytes each way, the frames posed in the map's frame and the joint ATE, --runs times "
                       "(share.md)")


def picked(args: argparse.Namespace) -> bool:
    return args.share


def run(args: argparse.Namespace, config, sequence, out) -> dict:
    import numpy as np

    from .steps.shared_map import format_table, share_runs

    rows = share_runs(sequence, runs=args.runs, progress=not args.quiet)
    report_table(out, "share", format_table(rows), args.argv)
    return {"share": {"rows": rows, "joint_ate_median": float(np.median([r["joint_ate"] for r in rows])),
                      "joint_ate_at_most_0_025": sum(r["joint_ate"] <= 0.025 for r in rows)}}
