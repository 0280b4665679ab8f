"""``twohr features eval | study | bench``: the feature-quality table, the 2HR parameter study, detector timings.

A thin shell over the detector core and the lab's ``evaluation``, ``quality`` and ``bench``; heavy modules
are imported inside the handlers so that ``twohr --help`` stays fast.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from twohr.paths import DEV_SEQUENCE

from ..stamp import stamp_line, write_stamp

DEFAULT_OUT = "runs/features"


def _bounded(parse, minimum: float, inclusive: bool, what: str):
    """An argparse ``type=`` that parses with ``parse`` and rejects values below ``minimum`` (or at it)."""
    def convert(text: str):
        try:
            value = parse(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        if not (value >= minimum if inclusive else value > minimum):
            raise argparse.ArgumentTypeError(f"expected {what}, got {value}")
        return value
    return convert


_positive_int = _bounded(int, 1, True, "a positive integer")
_non_negative_int = _bounded(int, 0, True, "a frame number (0 or more)")
_positive_float = _bounded(float, 0, False, "a positive number")


def _detector_conf(args: argparse.Namespace):
    """The ``detector`` config section: defaults, then --config, then --set, then --model/--input-scale/--threads."""
    from pydantic import ValidationError

    from twohr.config import DetectorConfig, load_config
    from twohr.errors import ConfigError, validation_problems

    conf = load_config(args.config, args.set).detector
    flags = {"model": args.model, "input_scale": args.input_scale, "threads": args.threads}
    # a study runs the network at input_scale on any machine (no latency budget): its figures are the features'
    fixed_scale = {"latency_budget_ms": None}
    try:
        return DetectorConfig.model_validate(conf.model_dump() | {k: v for k, v in flags.items() if v is not None}
                                             | fixed_scale)
    except ValidationError as exc:
        raise ConfigError(f"invalid detector option: {validation_problems(exc)}") from None


def _stop(args: argparse.Namespace) -> int | None:
    """The frame before which the pairs end: --start plus the --frames count."""
    return None if args.frames is None else args.start + args.frames


def _write(out: Path, name: str, payload: str) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    path = out / name
    path.write_text(payload)
    return path


def _eval(args: argparse.Namespace) -> int:
    from twohr.dataset import RGBDSequence

    from .plots import plot_table
    from .quality import feature_table, markdown_details, markdown_table, restrict

    sequence = RGBDSequence(args.sequence)
    conf = _detector_conf(args)
    table = feature_table(sequence, args.methods, args.deltas, args.step, args.start, _stop(args), args.threshold,
                          conf)
    out = Path(args.out)
    title = (f"Feature quality on {sequence.name}, frames [{table.frames[0]}, {table.frames[1]}) (pairs every "
             f"{table.step} frames, {table.frames_detected} frames detected), {table.threshold_px:g} px, GT extrinsic "
             f"{table.gt_extrinsic}; detector {conf.model} at input scale {conf.input_scale}")
    sections = [stamp_line(args.argv), "", f"## {title}", "", markdown_table(table), "", markdown_details(table)]
    if args.split_at is not None:
        for label, part in ((f"frames [{table.frames[0]}, {args.split_at})", restrict(table, 0, args.split_at)),
                            (f"frames [{args.split_at}, {table.frames[1]})", restrict(table, args.split_at))):
            sections += ["", f"### Only pairs within {label}", "", markdown_table(part), "", markdown_details(part)]
    text = "\n".join(sections) + "\n"
    print(text)
    paths = [_write(out, "feature_table.md", text), _write(out, "feature_table.json", table.model_dump_json(indent=1)),
             plot_table(table, out / "feature_table.png")]
    paths.append(write_stamp(out, args.argv))
    print("wrote " + ", ".join(map(str, paths)))
    return 0


def _study(args: argparse.Namespace) -> int:
    from twohr.dataset import RGBDSequence

    from .plots import plot_study
    from .quality import kmeans_study

    sequence = RGBDSequence(args.sequence)
    base = _detector_conf(args)
    result = kmeans_study(sequence, base, args.deltas, args.step, args.start, _stop(args), args.threshold)
    lines = [f"## 2HR parameter study on {sequence.name}, frames [{result.frames[0]}, {result.frames[1]}), "
             f"{result.frames_detected} frames, {result.threshold_px:g} px", "",
             "| parameter | value | " + " | ".join(f"%Rep Δ{d}" for d in result.deltas) + " | "
             + " | ".join(f"%Prec Δ{d}" for d in result.deltas) + " | correct matches Δ" + str(result.deltas[-1])
             + " | kp/frame | coverage |", "|" + "---|" * (5 + 2 * len(result.deltas))]
    last = str(result.deltas[-1])
    for p in [result.raw_r2d2] + result.points:
        lines.append(f"| {p.parameter} | {p.value:g} | "
                     + " | ".join(f"{p.by_delta[str(d)]['rep']:.1f}" for d in result.deltas) + " | "
                     + " | ".join(f"{p.by_delta[str(d)]['prec']:.1f}" for d in result.deltas)
                     + f" | {p.by_delta[last]['correct']:.0f} | {p.keypoints_per_frame:.0f} "
                     f"| {100 * p.coverage:.0f} % |")
    text = "\n".join([stamp_line(args.argv), "", *lines]) + "\n"
    print(text)
    out = Path(args.out)
    chosen = {"reliability_clusters": base.reliability_clusters, "repeatability_clusters": base.repeatability_clusters,
              "score_threshold": base.score_threshold, "floors": base.min_reliability}
    paths = [_write(out, "kmeans_study.md", text), _write(out, "kmeans_study.json", result.model_dump_json(indent=1)),
             plot_study(result, out / "kmeans_study.png", chosen)]
    paths.append(write_stamp(out, args.argv))
    print("wrote " + ", ".join(map(str, paths)))
    return 0


def _bench(args: argparse.Namespace) -> int:
    from twohr.dataset import RGBDSequence
    from twohr.errors import DatasetError

    from .bench import benchmark_detector, markdown_bench

    sequence = RGBDSequence(args.sequence)
    if not 0 <= args.frame < len(sequence):
        raise DatasetError(f"--frame {args.frame} is outside the sequence (0..{len(sequence) - 1})")
    image = sequence.read(args.frame).rgb
    result = benchmark_detector(image, args.models, args.scales, args.runs, args.threads or 2)
    result["sequence"] = str(sequence.root)
    result["frame"] = args.frame
    text = markdown_bench(result)
    print(text)
    out = Path(args.out)
    paths = [_write(out, "bench.json", json.dumps(result, indent=1)), _write(out, "bench.md", text + "\n")]
    paths.append(write_stamp(out, args.argv))
    print("wrote " + ", ".join(map(str, paths)))
    return 0


def _common(p: argparse.ArgumentParser, out_default: str = DEFAULT_OUT) -> None:
    p.add_argument("--sequence", default=DEV_SEQUENCE,
                   help=f"TUM-layout RGB-D sequence with groundtruth.txt (default {DEV_SEQUENCE})")
    p.add_argument("--out", default=out_default, help=f"output folder (default {out_default})")
    p.add_argument("--config", help="pipeline YAML; its detector section is the starting point")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="config override, e.g. --set detector.score_threshold=0.5 (repeatable)")
    p.add_argument("--model", help="keyframe network: auto (default: the fastest that meets the quality floor), "
                   "r2d2, faster2d2, faster2d2-int8, faster2d2-int8-coarse, student or a registered r2d2-kind model")
    p.add_argument("--input-scale", type=float, help="network input size relative to the image, e.g. 0.5")
    p.add_argument("--threads", type=_positive_int, help="onnxruntime threads (default 2)")


def _pairs(p: argparse.ArgumentParser) -> None:
    p.add_argument("--deltas", type=_positive_int, nargs="+", default=[1, 5, 10],
                   help="frame distances of the pairs (default 1 5 10)")
    p.add_argument("--step", type=_positive_int, default=10, help="a pair starts every STEP frames (default 10)")
    p.add_argument("--start", type=_non_negative_int, default=0, help="first frame (default 0)")
    p.add_argument("--frames", type=_positive_int,
                   help="use this many frames from --start (default: to the end of the sequence)")
    p.add_argument("--threshold", type=_positive_float, default=3.0,
                   help="pixel threshold for %%Rep and %%Prec (default 3)")


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``twohr features`` and its actions."""
    parser = sub.add_parser(
        "features", help="keypoint quality (paper Table 2), the 2HR parameter study, detector timings",
        description="Measure keypoints on real RGB-D frame pairs with ground-truth poses and depth: %Rep (keypoints "
        "of A that reproject within the threshold of a keypoint of B, over those in B's depth-checked view) and "
        "%Prec (mutual nearest-neighbour descriptor matches that reproject within the threshold).")
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)

    p = actions.add_parser("eval", help="the feature table: FAST, ORB, SIFT, R2D2, 2HR",
                           description="Table 2 of the paper on a sequence: %Rep and %Prec per frame distance, "
                           "keypoints and milliseconds per frame. Writes feature_table.{md,json,png} to --out.")
    _common(p)
    _pairs(p)
    p.add_argument("--methods", nargs="+", default=["FAST", "ORB", "SIFT", "R2D2", "2HR"],
                   choices=["FAST", "ORB", "SIFT", "R2D2", "2HR"], help="rows of the table (default: all)")
    p.add_argument("--split-at", type=_non_negative_int, metavar="FRAME",
                   help="also summarise the pairs before and after FRAME separately (e.g. frames the study "
                   "did not see)")
    p.set_defaults(func=_eval)

    p = actions.add_parser("study", help="the 2HR parameter study (k, T, score floors) as a plot",
                           description="Changes one 2HR parameter at a time from the configured defaults (k for "
                           "reliability and repeatability 1..10, T, the score floors) and scores each setting on "
                           "the same frame pairs. Writes kmeans_study.{md,json,png} to --out.")
    _common(p)
    _pairs(p)
    p.set_defaults(func=_study)

    p = actions.add_parser("bench", help="ms per frame of each network at full and half resolution, and the filter",
                           description="Median times of several interleaved runs on one real frame: each R2D2 network "
                           "against the unchanged exported graph, whole detect(), the 2HR filter on 5,000 points, "
                           "and ORB. Writes bench.{json,md} to --out.")
    p.add_argument("--sequence", default=DEV_SEQUENCE, help=f"sequence to take the frame from (default "
                   f"{DEV_SEQUENCE})")
    p.add_argument("--frame", type=_non_negative_int, default=0, help="frame index (default 0)")
    p.add_argument("--out", default=DEFAULT_OUT, help=f"output folder (default {DEFAULT_OUT})")
    p.add_argument("--models", nargs="+", default=["faster2d2_WASF_N16", "r2d2_WASF_N16", "r2d2_WASF_N16_int8"],
                   help="networks to time")
    p.add_argument("--scales", type=_positive_float, nargs="+", default=[1.0, 0.5],
                   help="input scales (default 1 0.5)")
    p.add_argument("--runs", type=_positive_int, default=5, help="timed runs per setting, median reported (default 5)")
    p.add_argument("--threads", type=_positive_int, help="onnxruntime threads (default 2)")
    p.set_defaults(func=_bench)
