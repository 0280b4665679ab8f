"""The accuracy study of the camera-rate schedule: ATE, RPE, jitter, scale and outliers, each variant run
several times (the default schedule's worker threads make runs differ), medians reported::

    .venv/bin/python -m twohr_lab.tracking.accuracy --runs 3 --out runs/accuracy \\
        --variant "integer keypoints=detector.subpixel=false" \\
        --variant "every 2nd frame=--step=2" --variant "from frame 280=--start=280"

A variant is ``name=key=value[;key=value...]``; ``--start=N`` and ``--step=N`` there pick the frames instead of
the config. Writes ``accuracy.md`` (stamped with the command and commit), ``accuracy.json`` and ``accuracy.png``
into ``--out``; no trajectories.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from twohr.config import load_config
from twohr.errors import ConfigError, TwohrError

from ..stamp import write_study
from .sensitivity import DEFAULT_SEQUENCE

#: a pose farther than this from the ground truth counts as an outlier (the issue's spikes were 5 and 8 cm)
OUTLIER_M = 0.04


def parse_variant(item: str) -> tuple[str, list[str], int, int]:
    """``name=key=value;key=value`` -> (name, config overrides, start, step)."""
    name, sep, spec = item.partition("=")
    if not name or not sep:
        raise ConfigError(f"--variant {item!r} is not of the form NAME=key=value[;key=value] (or NAME= for none)")
    overrides, start, step = [], 0, 1
    for part in filter(None, (p.strip() for p in spec.split(";"))):
        if part.startswith("--start="):
            start = int(part.removeprefix("--start="))
        elif part.startswith("--step="):
            step = int(part.removeprefix("--step="))
        else:
            overrides.append(part)
    return name.strip(), overrides, start, step


def run_metrics(sequence, config, start: int = 0, step: int = 1, frames: int | None = None) -> dict:
    """One run of the pipeline (``frames`` frames from ``start``, every ``step``-th; None = to the end) and its
    figures against the camera-frame ground truth."""
    from twohr.evaluation import evaluate
    from twohr_app.pipeline import run_sequence
    from twohr_services.tracker.trajectory import TRACKED_STATUSES

    stop = None if frames is None else start + frames * step
    run = run_sequence(sequence, config, start=start, stop=stop, step=step, progress=False)
    extrinsic = sequence.default_gt_extrinsic()
    gt = sequence.ground_truth(extrinsic)
    refined, arrays = evaluate(gt, run.trajectory, gt_extrinsic=extrinsic)
    online, _ = evaluate(gt, run.online, gt_extrinsic=extrinsic)
    errors, stamps = arrays["ate"], arrays["est"].stamps - sequence.stamps[0]
    return {
        "ate": refined.ate.rmse, "ate_online": online.ate.rmse, "ate_max": refined.ate.max,
        "rpe_frame": refined.rpe_frame.rmse, "rpe_1s": refined.rpe_1s.rmse, "jitter": refined.jitter.rmse,
        "rpe_frame_online": online.rpe_frame.rmse, "sim3_scale": refined.sim3_scale,
        "outliers": int((errors > OUTLIER_M).sum()),
        "outlier_seconds": sorted({round(float(t), 1) for t in stamps[errors > OUTLIER_M]}),
        "tracked_percent": run.tracked_percent, "frames": len(run.stats),
        "fps": len(run.stats) / run.wall_s if run.wall_s > 0 else float("nan"),
        "untracked_frames": sum(s.status not in TRACKED_STATUSES for s in run.stats),
    }


METRICS = ("ate", "ate_online", "ate_max", "rpe_frame", "rpe_1s", "jitter", "sim3_scale", "outliers", "fps")


def summarise(runs: list[dict]) -> dict:
    """Medians over the runs of one variant."""
    return {key: float(np.median([r[key] for r in runs])) for key in METRICS}


def format_table(rows: list[dict]) -> str:
    lines = ["| variant | runs | ATE (m) | ATE online (m) | ATE max (m) | RPE 1 frame (mm) | RPE 1 s (mm) | "
             "jitter (mm) | Sim(3) scale | poses > 4 cm | FPS | ATE of each run (m) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        m = row["median"]
        each = ", ".join(f"{r['ate']:.4f}" for r in row["runs"])
        lines.append(f"| {row['variant']} | {len(row['runs'])} | {m['ate']:.4f} | {m['ate_online']:.4f} | "
                     f"{m['ate_max']:.3f} | {1000 * m['rpe_frame']:.2f} | {1000 * m['rpe_1s']:.1f} | "
                     f"{1000 * m['jitter']:.2f} | {m['sim3_scale']:.3f} | {m['outliers']:.0f} | {m['fps']:.1f} | "
                     f"{each} |")
    return "\n".join(lines)


def plot(path: Path, rows: list[dict]) -> None:
    """ATE and RPE over one frame of every run, per variant (dots: runs; bars: medians)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 0.5 * len(rows) + 1.6), sharey=True)
    for ax, key, unit, scale in ((axes[0], "ate", "ATE RMSE (cm)", 100), (axes[1], "rpe_frame", "RPE 1 frame (mm)",
                                                                           1000)):
        for y, row in enumerate(rows):
            ax.barh(y, scale * row["median"][key], color="#9ecae1")
            ax.plot([scale * r[key] for r in row["runs"]], [y] * len(row["runs"]), "k.")
        ax.set_xlabel(unit)
        ax.grid(axis="x", alpha=0.3)
    axes[0].set_yticks(range(len(rows)), [r["variant"] for r in rows])
    axes[0].invert_yaxis()
    fig.suptitle("camera-rate schedule on the dev sequence: medians (bars) and runs (dots)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m twohr_lab.tracking.accuracy", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sequence", default=DEFAULT_SEQUENCE, help="TUM-layout RGB-D folder with ground truth")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config value for every variant")
    parser.add_argument("--variant", action="append", default=[], metavar="NAME=KEY=VALUE[;KEY=VALUE]",
                        help="a variant besides the defaults (repeatable); --start=N / --step=N pick frames")
    parser.add_argument("--frames", type=int, default=None, help="process at most this many frames per run")
    parser.add_argument("--runs", type=int, default=3, help="runs per variant (median reported)")
    parser.add_argument("--out", default="runs/accuracy", help="output folder (default runs/accuracy)")
    parser.add_argument("--quiet", action="store_true", help="do not print runs as they finish")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    argv = list(sys.argv[1:] if argv is None else argv)
    program = "python -m twohr_lab.tracking.accuracy"
    rows = []
    try:
        from twohr.dataset import RGBDSequence

        if args.runs < 1 or (args.frames is not None and args.frames < 3):
            raise ConfigError("--runs must be >= 1 and --frames >= 3")
        variants = [("defaults", [], 0, 1)] + [parse_variant(v) for v in args.variant]
        sequence = RGBDSequence(args.sequence)
        if not sequence.has_ground_truth():
            raise ConfigError(f"{sequence.root} has no groundtruth.txt: the accuracy study needs it")
        configs = [(name, load_config(None, [*args.set, *overrides]), start, step)
                   for name, overrides, start, step in variants]
        for name, config, start, step in configs:
            runs = []
            for _ in range(args.runs):
                runs.append(run_metrics(sequence, config, start, step, args.frames))
                if not args.quiet:
                    print(f"{name}: ATE {runs[-1]['ate']:.4f} m, RPE 1 frame {1000 * runs[-1]['rpe_frame']:.2f} mm, "
                          f"FPS {runs[-1]['fps']:.1f}", flush=True)
            rows.append({"variant": name, "start": start, "step": step, "runs": runs, "median": summarise(runs)})
    except (TwohrError, ValueError) as exc:
        print(f"accuracy: error: {exc}", file=sys.stderr)
        return 2
    table = format_table(rows)
    out = write_study(args.out, "accuracy", table, rows, argv, program)
    plot(out / "accuracy.png", rows)
    print(table)
    print(f"written: {out / 'accuracy.md'}, accuracy.json, accuracy.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
