"""``twohr matcher train | eval | bench``: train the Siamese matcher, produce the matching table, time it.

A thin shell: it composes the detector core (keypoints, cached once) with the matcher's data,
training and evaluation modules. Heavy modules (torch, onnxruntime, the detector) load lazily.
"""

from __future__ import annotations

import argparse
import json
import time
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

from twohr.paths import DEV_SEQUENCE

from ..stamp import provenance, stamp_line, write_stamp

if TYPE_CHECKING:
    import numpy as np

DEFAULT_CACHE = "runs/matcher_cache"
TAU_GRID = [round(0.025 * i, 3) for i in range(37)]  # 0 to 0.9
RATIOS = [0.7, 0.8, 0.9]


# ----------------------------------------------------------------------------- shared plumbing


def _detector_conf(args: argparse.Namespace):
    """The ``detector`` section of the pipeline config: defaults, then --config, then --set."""
    from twohr.config import load_config

    # keypoints at input_scale on any machine (no latency budget): the study's figures are the matcher's
    return load_config(args.config, args.set).detector.model_copy(update={"latency_budget_ms": None})


def _split_conf(args: argparse.Namespace):
    from twohr.errors import ConfigError

    from .data import SplitConfig

    if any(d <= 0 or d % args.step for d in args.deltas):
        raise ConfigError(f"--deltas {args.deltas} must be positive multiples of --step {args.step}")
    return SplitConfig(step=args.step, deltas=args.deltas)


def _splits(args: argparse.Namespace, split_conf) -> dict[str, list[int]]:
    """Train/val/test frame indices of the --frames frames from --start (split by time)."""
    from twohr.dataset import RGBDSequence

    from .data import split_frames

    available = len(RGBDSequence(args.sequence)) - args.start
    count = available if args.frames is None else min(args.frames, available)
    if count < 1:
        from twohr.errors import ConfigError

        raise ConfigError(f"--start {args.start} leaves no frames in {args.sequence}")
    return {name: [args.start + i for i in frames] for name, frames in split_frames(count, split_conf).items()}


def _open_cache(args: argparse.Namespace, frames: list[int]):
    return open_cache(args.sequence, _detector_conf(args), args.cache, frames)


def open_cache(sequence_path: str | Path, detector_conf, root: str | Path, frames: list[int]):
    """The sequence's keypoint cache under ``root``, filled for ``frames`` (runs the detector only where needed);
    the vocabulary study (``twohr vocab``) reads the same cache."""
    from twohr.dataset import RGBDSequence

    from .data import KeypointCache

    cache = KeypointCache(RGBDSequence(sequence_path), detector_conf, root)
    if cache.missing(frames):
        from twohr_services.detector.core import build_detector

        print(f"detecting keypoints on {len(cache.missing(frames))} frames (cached in {cache.folder})")
        cache.fill(frames, build_detector(cache.detector_conf))
    return cache


def _add_data_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sequence", default=DEV_SEQUENCE, help="TUM-layout RGB-D folder with groundtruth.txt")
    p.add_argument("--cache", default=DEFAULT_CACHE, help="keypoint cache folder")
    _add_config_arguments(p)
    p.add_argument("--start", type=int, default=0, help="first frame")
    p.add_argument("--frames", type=int, default=None, help="use this many frames from --start (default: all); "
                   "the split by time applies to them")
    p.add_argument("--step", type=int, default=2, help="use every n-th frame")
    p.add_argument("--deltas", type=int, nargs="+", default=[2, 4, 6, 10],
                   help="frame gaps of the pairs, multiples of --step")


def _add_config_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", help="pipeline YAML; its detector section gives the keypoints")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="config override, e.g. --set detector.max_keypoints=1000 (repeatable)")


def _arguments(args: argparse.Namespace) -> dict:
    """The parsed command-line arguments, for the reports."""
    return {k: v for k, v in vars(args).items() if k not in ("func", "verbose", "argv")}


def _sha256(path: Path) -> str:
    from twohr.models import sha256_of

    return sha256_of(path)


# ----------------------------------------------------------------------------- train


def choose_threshold(sweep: list[dict], baseline: dict) -> tuple[float, str]:
    """tau from the validation sweep: the middle of the window where the Siamese matcher beats mutual NN on both
    M.S.@3px and MMA@3px (precision). The middle, not an edge, leaves a margin on both sides for unseen data.
    Without such a window: the tau with the smallest worst relative shortfall."""
    winning = [row["tau"] for row in sweep
               if row["ms_3px"] >= baseline["ms_3px"] and row["mma_3px"] >= baseline["mma_3px"]]
    if winning:
        middle = (min(winning) + max(winning)) / 2
        return min(winning, key=lambda tau: abs(tau - middle)), "middle of the window that beats mutual NN on both"

    def shortfall(row: dict) -> float:
        return max(1 - row["ms_3px"] / baseline["ms_3px"], 1 - row["mma_3px"] / baseline["mma_3px"])

    return min(sweep, key=shortfall)["tau"], "no tau beats mutual NN on both: smallest shortfall"


def _train(args: argparse.Namespace) -> int:
    from .data import LabelConfig, build_pair_set, frame_pairs

    try:
        from .training import TrainConfig, export_onnx, plot_training, train_siamese
    except ModuleNotFoundError as exc:
        from twohr.errors import TwohrError

        raise TwohrError(f"training needs the train extra ({exc.name} is missing): pip install -e '.[train]'") from None

    split_conf = _split_conf(args)
    label_conf = LabelConfig(max_anchors=args.max_anchors)
    train_conf = TrainConfig(epochs=args.epochs, seed=args.seed, batch_size=args.batch_size,
                             learning_rate=args.learning_rate, channels=args.channels, threads=args.threads)
    splits = _splits(args, split_conf)
    cache = _open_cache(args, splits["train"] + splits["val"] + splits["test"])
    pairs = {name: frame_pairs(frames, split_conf.deltas) for name, frames in splits.items()}
    sets = {name: build_pair_set(cache, pairs[name], label_conf, seed=args.seed + i)
            for i, name in enumerate(("train", "val", "test"))}
    for name, pair_set in sets.items():
        print(f"{name:5} frames {splits[name][0]}-{splits[name][-1]}: {pair_set.counts()}")

    result = train_siamese(sets["train"], sets["val"], train_conf)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    plot = plot_training(result, out / "training_curves.png")
    metrics = _metrics_at_half(result.model, sets)

    model_out = Path(args.model_out)
    export_onnx(result.model, model_out, {"trained_on": f"{cache.sequence.name} frames {splits['train'][0]}-"
                                          f"{splits['train'][-1]}", "command": "twohr matcher train"})
    threshold = _validation_threshold(args, cache, pairs["val"], model_out, out)

    report = {
        "arguments": _arguments(args),
        "sequence": str(cache.sequence.root), "detector": cache.detector_conf.model_dump(),
        "split": {name: [frames[0], frames[-1], len(frames)] for name, frames in splits.items()},
        "split_config": split_conf.model_dump(), "labels": label_conf.model_dump(), "train": train_conf.model_dump(),
        "pair_counts": {name: s.counts() for name, s in sets.items()},
        "history": result.history, "best_epoch": result.best_epoch, "train_seconds": result.seconds,
        "metrics_at_0.5": metrics,
        "val_threshold_sweep": threshold["sweep"], "val_mutual_nn": threshold["baseline"],
        "val_ratio_test": threshold["ratios"],
        "chosen_threshold": threshold["tau"], "threshold_rule": threshold["rule"], "candidates": args.candidates,
        "model": str(model_out), "sha256": _sha256(model_out),
        "model_bytes": model_out.stat().st_size,
        "parameters": sum(p.numel() for p in result.model.parameters()),
    }
    (out / "training.json").write_text(json.dumps(report, indent=2))
    write_stamp(out, args.argv)
    _print_training(report, result, metrics, threshold)
    print(f"model:  {model_out} sha256 {report['sha256']}")
    print(f"report: {out / 'training.json'}\nplots:  {plot}, {threshold['plot']}")
    return 0


def _metrics_at_half(model, sets: dict) -> dict:
    """Loss, classification metrics at score 0.5 and the mean score by kind of pair, on the val and test pairs."""
    from .training import classification_metrics, predict

    metrics = {}
    for name in ("val", "test"):
        scores, loss = predict(model, sets[name])
        metrics[name] = {"loss": loss, **classification_metrics(scores, sets[name].label)}
        metrics[name]["by_kind_mean_score"] = {kind: float(scores[sets[name].kind == code].mean())
                                               for code, kind in enumerate(("positive", "hard_negative", "random"))}
    return metrics


def _validation_threshold(args: argparse.Namespace, cache, val_pairs, model_out: Path, out: Path) -> dict:
    """tau on the validation frame pairs only (the held-out test pairs are for `twohr matcher eval`): the sweep,
    mutual NN and the ratio tests on the same pairs, the tau chosen and why, and the sweep's plot."""
    from twohr.config import MatcherConfig
    from twohr_services.matcher.core import SiameseMatcher, mutual_nn, ratio_test

    from .evaluation import evaluate_matchers, threshold_sweep

    baselines = {"mutual NN": lambda a, b: mutual_nn(a, b)}
    for ratio in RATIOS:
        baselines[f"ratio {ratio:g}"] = partial(ratio_test, ratio=ratio)
    baseline_summaries = evaluate_matchers(cache, val_pairs, baselines)[0]
    baseline = baseline_summaries["mutual NN"]
    ratio_rows = [{"ratio": ratio, "ms_3px": baseline_summaries[f"ratio {ratio:g}"].matching_score["3px"],
                   "mma_3px": baseline_summaries[f"ratio {ratio:g}"].mma["3px"]} for ratio in RATIOS]
    siamese = SiameseMatcher(MatcherConfig(candidates=args.candidates), model_file=model_out)
    sweep = [{"tau": tau, "ms_3px": s.matching_score["3px"], "mma_3px": s.mma["3px"],
              "matches_per_pair": s.matches_per_pair}
             for tau, s in threshold_sweep(cache, val_pairs, siamese, TAU_GRID).items()]
    baseline_row = {"ms_3px": baseline.matching_score["3px"], "mma_3px": baseline.mma["3px"],
                    "matches_per_pair": baseline.matches_per_pair}
    tau, rule = choose_threshold(sweep, baseline_row)
    plot = _plot_sweep(sweep, baseline_row, ratio_rows, tau, out / "threshold_sweep_val.png")
    return {"sweep": sweep, "baseline": baseline_row, "ratios": ratio_rows, "tau": tau, "rule": rule, "plot": plot}


def _print_training(report: dict, result, metrics: dict, threshold: dict) -> None:
    print(f"trained {report['parameters']} parameters in {result.seconds:.0f} s (kept epoch {result.best_epoch})")
    for name in ("val", "test"):
        m = metrics[name]
        print(f"{name:4} pairs at score 0.5: accuracy {m['accuracy']:.3f} precision {m['precision']:.3f} "
              f"recall {m['recall']:.3f} (loss {m['loss']:.4f})")
    baseline_row, sweep = threshold["baseline"], threshold["sweep"]
    print(f"validation M.S./MMA @3px: mutual NN {baseline_row['ms_3px']:.3f}/{baseline_row['mma_3px']:.3f}; "
          "Siamese " + ", ".join(f"tau {r['tau']:g}: {r['ms_3px']:.3f}/{r['mma_3px']:.3f}" for r in sweep[::4]))
    print(f"chosen tau {threshold['tau']:g} ({threshold['rule']}); use it as matcher.threshold")


def _plot_sweep(sweep: list[dict], baseline: dict, ratio_rows: list[dict], tau: float, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4.5))
    ms = [r["ms_3px"] for r in sweep]
    mma = [r["mma_3px"] for r in sweep]
    ax.plot(ms, mma, "o-", ms=3, label="Siamese, tau = 0 ... 0.9")
    chosen = next(r for r in sweep if r["tau"] == tau)
    ax.plot(chosen["ms_3px"], chosen["mma_3px"], "r*", ms=14, label=f"chosen tau = {tau:g}")
    ax.plot(baseline["ms_3px"], baseline["mma_3px"], "ks", ms=8, label="mutual NN")
    ax.plot([r["ms_3px"] for r in ratio_rows], [r["mma_3px"] for r in ratio_rows], "^--", color="C2", ms=6,
            label="ratio test (mutual), " + ", ".join(f"{r['ratio']:g}" for r in ratio_rows))
    ax.axvline(baseline["ms_3px"], color="k", lw=0.5, ls=":")
    ax.axhline(baseline["mma_3px"], color="k", lw=0.5, ls=":")
    ax.set_xlabel("M.S. @3px (correct / keypoints in shared view)")
    ax.set_ylabel("MMA @3px (precision)")
    ax.set_title("validation frame pairs: choosing tau")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# ----------------------------------------------------------------------------- eval


def _eval(args: argparse.Namespace) -> int:
    from twohr.config import MatcherConfig
    from twohr_services.matcher.core import SiameseMatcher, mutual_nn, ratio_test

    from .data import LabelConfig, frame_pairs
    from .evaluation import evaluate_matchers, format_table, summarize

    split_conf = _split_conf(args)
    conf = MatcherConfig(candidates=args.candidates,
                         **({"threshold": args.threshold} if args.threshold is not None else {}))
    siamese = SiameseMatcher(conf, model_file=args.model_file)  # load before the long keypoint detection
    rerank_only = SiameseMatcher(conf.model_copy(update={"threshold": 0.0}), model_file=args.model_file)
    frames = _splits(args, split_conf)[args.split]
    cache = _open_cache(args, frames)
    pairs = frame_pairs(frames, split_conf.deltas)
    matchers = {
        "mutual NN": lambda a, b: mutual_nn(a, b),
        f"ratio test {args.ratio} (mutual)": lambda a, b: ratio_test(a, b, args.ratio),
        f"Siamese k={conf.candidates}, tau=0 (re-rank only)": rerank_only.match,
        f"Siamese k={conf.candidates}, tau={conf.threshold:g}": siamese.match,
    }
    thresholds = [float(t) for t in range(1, 11)]
    summaries, rows = evaluate_matchers(cache, pairs, matchers, thresholds)
    table = format_table(summaries, keys=["1px", "3px", "5px"])
    by_delta = {}
    for delta in split_conf.deltas:
        by_delta[delta] = {name: summarize(name, [r for r in results if r.frame_b - r.frame_a == delta])
                           for name, results in rows.items()}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"table3_{args.split}"
    lines = [f"# Matching on {cache.sequence.name}, {args.split} split (frames {frames[0]}-{frames[-1]}, "
             f"{len(rows['mutual NN'])} frame pairs, gaps {split_conf.deltas} frames)", "",
             f"Keypoints: 2HR ({cache.detector_conf.model}, max {cache.detector_conf.max_keypoints}); "
             f"M.S. = correct matches / keypoints in the shared view; MMA = correct / verifiable matches; "
             f"means over frame pairs.", "", table, ""]
    gate = LabelConfig().min_pair_repeatability
    gated = {name: summarize(name, results, gate) for name, results in rows.items()}
    kept = next(iter(gated.values())).frame_pairs
    lines += [f"## frame pairs whose ground truth passes the check ({kept} of {len(rows['mutual NN'])})", "",
              f"Keypoint repeatability at 3 px >= {gate} (no descriptors involved; on the other pairs the "
              "ground-truth pose is several pixels off, see MODEL_CARD.md).", "",
              format_table(gated, keys=["1px", "3px", "5px"]), ""]
    for delta, summaries_delta in by_delta.items():
        lines += [f"## gap {delta} frames ({delta / 30:.2f} s)", "", format_table(summaries_delta,
                                                                                   keys=["1px", "3px", "5px"]), ""]
    (out / f"{stem}.md").write_text("\n".join([stamp_line(args.argv), "", *lines]))
    write_stamp(out, args.argv)
    (out / f"{stem}.json").write_text(json.dumps({
        "arguments": _arguments(args), "pairs": len(rows["mutual NN"]),
        "summaries": {k: v.model_dump() for k, v in summaries.items()},
        "summaries_gt_checked": {k: v.model_dump() for k, v in gated.items()}, "gt_check_min_repeatability": gate,
        "by_delta": {d: {k: v.model_dump() for k, v in s.items()} for d, s in by_delta.items()},
    }, indent=2))
    plot = _plot_curves(summaries, out / f"{stem}.png", f"{cache.sequence.name}, {args.split} split")
    print(table)
    print(f"table:  {out / (stem + '.md')}\nplot:   {plot}")
    return 0


def _plot_curves(summaries: dict, path: Path, title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for name, s in summaries.items():
        px = [float(k[:-2]) for k in s.mma]
        axes[0].plot(px, list(s.mma.values()), "o-", ms=3, label=name)
        axes[1].plot(px, list(s.matching_score.values()), "o-", ms=3, label=name)
    for ax, label in zip(axes, ("MMA (correct / matches)", "M.S. (correct / keypoints in shared view)"), strict=True):
        ax.set_xlabel("reprojection threshold (px)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.set_ylim(0, 1)
    axes[0].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# ----------------------------------------------------------------------------- bench


def benchmark_matcher(conf=None, num_keypoints: int = 1000, repeats: int = 20,
                      descriptors: tuple[np.ndarray, np.ndarray] | None = None, seed: int = 0) -> dict:
    """Milliseconds per frame pair (median of ``repeats``) of the Siamese matcher and the baselines.

    ``descriptors``: a real (desc_a, desc_b) pair, cut to ``num_keypoints`` each; without it, random unit
    vectors. Mutual NN is the baseline measured in the same run; ``ratio_to_mutual_nn`` divides by it.
    """
    import numpy as np

    from twohr.config import MatcherConfig
    from twohr_services.matcher.core import SiameseMatcher, knn_candidates, mutual_best, mutual_nn, ratio_test

    conf = conf or MatcherConfig()
    if descriptors is None:
        rng = np.random.default_rng(seed)
        descriptors = tuple(rng.standard_normal((num_keypoints, 128)).astype(np.float32) for _ in range(2))
        descriptors = tuple(d / np.linalg.norm(d, axis=1, keepdims=True) for d in descriptors)
        source = "random unit vectors"
    else:
        source = "real descriptors"
    desc_a, desc_b = (np.ascontiguousarray(d[:num_keypoints], np.float32) for d in descriptors)
    siamese = SiameseMatcher(conf)

    def timed(fn) -> float:
        fn()  # warm-up
        samples = []
        for _ in range(repeats):
            start = time.perf_counter()
            fn()
            samples.append(time.perf_counter() - start)
        return float(np.median(samples) * 1000)

    idx_a, idx_b = knn_candidates(desc_a, desc_b, conf.candidates)
    scores = siamese.score(desc_a, desc_b, idx_a, idx_b)
    result = {
        "keypoints": [len(desc_a), len(desc_b)], "descriptors": source, "candidates": conf.candidates,
        "candidate_pairs": len(idx_a), "repeats": repeats, "threads": conf.threads,
        "ms": {
            "mutual_nn": timed(lambda: mutual_nn(desc_a, desc_b)),
            "ratio_test": timed(lambda: ratio_test(desc_a, desc_b, conf.ratio)),
            "siamese": timed(lambda: siamese.match(desc_a, desc_b)),
            "siamese_candidates_knn": timed(lambda: knn_candidates(desc_a, desc_b, conf.candidates)),
            "siamese_head_onnx": timed(lambda: siamese.score(desc_a, desc_b, idx_a, idx_b)),
            "siamese_mutual_best": timed(lambda: mutual_best(idx_a, idx_b, scores)),
        },
    }
    result["ratio_to_mutual_nn"] = {k: v / result["ms"]["mutual_nn"] for k, v in result["ms"].items()}
    return result


def _bench(args: argparse.Namespace) -> int:
    import numpy as np

    from twohr.config import MatcherConfig

    descriptors = None
    if args.sequence:
        cache = _open_cache(args, args.pair)
        descriptors = tuple(cache.load(i).keypoints.descriptors for i in args.pair)
    runs = []
    for _ in range(args.runs):
        runs.append(benchmark_matcher(MatcherConfig(candidates=args.candidates), args.keypoints, args.repeats,
                                      descriptors))
    result = runs[0] | {"runs": args.runs,
                        "ms": {k: float(np.median([r["ms"][k] for r in runs])) for k in runs[0]["ms"]}}
    result["ratio_to_mutual_nn"] = {k: v / result["ms"]["mutual_nn"] for k, v in result["ms"].items()}
    result["ms_per_run"] = {k: [r["ms"][k] for r in runs] for k in runs[0]["ms"]}
    print(f"{result['keypoints'][0]}x{result['keypoints'][1]} keypoints ({result['descriptors']}), "
          f"k={result['candidates']} -> {result['candidate_pairs']} candidate pairs; median of {args.runs} runs "
          f"x {args.repeats} repeats")
    print(f"{'method':26} {'ms/pair':>8} {'x mutual NN':>12}")
    for key, ms in result["ms"].items():
        print(f"{key:26} {ms:8.2f} {result['ratio_to_mutual_nn'][key]:12.2f}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({**result, "provenance": provenance(args.argv)}, indent=2))
        print(f"json:   {args.json}")
    return 0


# ----------------------------------------------------------------------------- registration


def register(sub: argparse._SubParsersAction) -> None:
    matcher = sub.add_parser(
        "matcher", help="train, evaluate and time the Siamese descriptor matcher",
        description="The paper's Siamese matcher (§3.3): a learned similarity over descriptor pairs that rejects "
        "wrong nearest-neighbour matches. Labels come from real RGB-D frames with ground-truth poses.")
    msub = matcher.add_subparsers(dest="matcher_command", metavar="ACTION", required=True)

    p = msub.add_parser(
        "train", help="label real RGB-D pairs, train the network, export ONNX, choose tau on validation",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description="Keypoints (2HR) are detected once per frame and cached. Frames are split by time: "
        "train 0-70 %, validation 70-80 % (model selection and tau), held-out test 80-100 %. "
        "A pair is positive when each keypoint reprojects within 3 px of the other and the depths agree; "
        "negatives are hard (descriptor nearest neighbours) and random. Needs the train extra (torch, onnx).")
    _add_data_arguments(p)
    p.add_argument("--out", default="runs/matcher/train", help="folder for training.json and training_curves.png")
    p.add_argument("--model-out", default="runs/matcher/siamese_2hr.onnx",
                   help="ONNX file to write; services/matcher/siamese_2hr.onnx replaces the shipped model")
    p.add_argument("--epochs", type=int, default=4)
    p.add_argument("--batch-size", type=int, default=2048)
    p.add_argument("--channels", type=int, default=8, help="Conv1d channels of the Siamese branch")
    p.add_argument("--threads", type=int, default=1, help="torch threads (1 is fastest on a shared 2-core machine)")
    p.add_argument("--learning-rate", type=float, default=3e-3)
    p.add_argument("--max-anchors", type=int, default=100, help="anchor keypoints sampled per frame pair")
    p.add_argument("--candidates", type=int, default=3, help="k nearest descriptors scored per keypoint (for tau)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_train)

    p = msub.add_parser(
        "eval", help="the matching table (M.S., MMA at 1/3/5 px): Siamese vs mutual NN vs ratio test",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description="Matches cached 2HR keypoints of real frame pairs and scores them with ground-truth "
        "geometry. Default: the held-out test split (last 20 % of the frames).")
    _add_data_arguments(p)
    p.add_argument("--split", choices=["train", "val", "test"], default="test")
    p.add_argument("--model-file", help="Siamese ONNX to evaluate (none: the registered siamese_2hr)")
    p.add_argument("--threshold", type=float, help="tau (none: matcher.threshold of MatcherConfig)")
    p.add_argument("--candidates", type=int, default=3, help="k nearest descriptors scored per keypoint")
    p.add_argument("--ratio", type=float, default=0.8, help="Lowe ratio of the ratio-test baseline")
    p.add_argument("--out", default="runs/matcher/eval", help="folder for table3_<split>.md/.json/.png")
    p.set_defaults(func=_eval)

    p = msub.add_parser(
        "bench", help="milliseconds per frame pair at 1000x1000 keypoints, against mutual NN",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description="Times the Siamese matcher (and its stages) and the baselines on one descriptor pair; "
        "reports medians and the ratio to mutual NN measured in the same run.")
    p.add_argument("--sequence", default=DEV_SEQUENCE,
                   help="take real descriptors from two frames of this sequence ('' = random unit vectors)")
    p.add_argument("--cache", default=DEFAULT_CACHE, help="keypoint cache folder")
    _add_config_arguments(p)
    p.add_argument("--pair", type=int, nargs=2, default=[100, 102], metavar=("A", "B"), help="the two frames")
    p.add_argument("--keypoints", type=int, default=1000, help="keypoints per frame (real ones are cut to this)")
    p.add_argument("--candidates", type=int, default=3)
    p.add_argument("--repeats", type=int, default=20, help="timed calls per run")
    p.add_argument("--runs", type=int, default=5, help="runs; the report gives the median over runs")
    p.add_argument("--json", help="write the result here")
    p.set_defaults(func=_bench)
