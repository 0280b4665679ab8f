"""``twohr bench``: the command line of the bench's studies (:mod:`twohr_lab.bench`).

Two spellings pick a study. ``twohr bench <study> [options]`` names it, with that study's options alone. The flags
of before still work on ``twohr bench`` itself: ``--fleet N``, ``--share``, ``--soak MINUTES``, ``--live``, ``--bus``,
``--view-tls``, ``--view``, ``--networks``, ``--ablations``, and none of them for throughput; where several are given,
the first of that list wins, as it always did. Every study shares ``twohr run``'s options and ``--runs``, and writes
its part of ``bench.json`` (with the provenance) into ``--out`` (default runs/bench).
"""

from __future__ import annotations

import argparse

from . import ablations, bus, fleet, live, networks, share, soak, throughput, view, view_tls
from .common import add_common_options, output_folder, write_bench_json

#: the studies, in the order their flags pick one when several are given (throughput: when none is)
STUDIES = (fleet, share, soak, live, bus, view_tls, view, networks, ablations, throughput)
#: the studies by name, in the order ``twohr bench --help`` lists them
BY_NAME = {study.NAME: study for study in (throughput, ablations, networks, view, view_tls, bus, live, soak, fleet,
                                           share)}


def chosen_study(args: argparse.Namespace):
    """The study module ``args`` asks for: the one named, else the first whose flag was given."""
    if getattr(args, "study", None):
        return BY_NAME[args.study]
    return next(study for study in STUDIES if study.picked(args))


def main(args: argparse.Namespace) -> int:
    """Run the chosen study and write ``bench.json``."""
    from twohr_app.commands.run import load_config_and_sequence

    study = chosen_study(args)
    config, sequence = load_config_and_sequence(args)
    out = output_folder(args)
    report = study.run(args, config, sequence, out)
    write_bench_json(out, report, args.argv)
    return 0


def build_parser(p: argparse.ArgumentParser) -> None:
    """Every study's options on ``twohr bench`` (each study's flag picks it, as before), and ``twohr bench <study>``
    with that study's options alone."""
    add_common_options(p)
    for study in BY_NAME.values():
        study.add_arguments(p.add_argument_group(f"{study.NAME}: {study.HELP}"), legacy=True)
    studies = p.add_subparsers(dest="study", metavar="STUDY", required=False,
                               title="studies (twohr bench STUDY --help; without one, the flags above pick it)")
    for name, study in BY_NAME.items():
        sp = studies.add_parser(name, help=study.HELP, description=study.__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
        add_common_options(sp)
        study.add_arguments(sp)
        for action in sp._actions:  # what is not given keeps the value of twohr bench's own parser
            if not isinstance(action, argparse._HelpAction):
                action.default = argparse.SUPPRESS
    p.set_defaults(func=main)


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``twohr bench``."""
    p = sub.add_parser("bench", help="throughput and per-stage latency (or --ablations: the accuracy table)",
                       usage="%(prog)s [options]  or  %(prog)s STUDY [options]",
                       description="Without --ablations: FPS, per-stage ms (median, p90) and peak RSS of the pipeline "
                       "over --frames frames, --runs times, each paired with an ORB baseline run for a ratio. With "
                       "--ablations: ATE RMSE, S.D., % tracked and ms/frame of ORB, R2D2, 2HR, 2HR+YOLO and the "
                       "full pipeline on the same tracker. Each study is also a subcommand: twohr bench STUDY.")
    build_parser(p)
