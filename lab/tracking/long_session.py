"""A long session in one place, replayed in this process: the map's working set, its landmark rows and the
process's memory, every ``--every`` frames, with and without each ``--config`` (issue 50's "culling keeps long
sessions bounded").

``python -m twohr_lab.tracking.long_session --sequence runs/sequences/rgbd_bonn_crowd_dev_x6 --every 560 \\
    --config reuse= --config every-row=tracker.reuse_landmark_rows=false --out runs/long``

Make the sequence with ``python -m twohr_lab.tracking.backwards --repeat 6``. Each configuration runs once, one
after the other, in a fresh process (so one's memory does not carry into the next). Writes ``rows.tsv`` (one row
per configuration and checkpoint), ``long_session.md`` (the table and the refined and online ATE) and
``long_session.png`` (landmark rows and RSS over the frames).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

COLUMNS = ("config", "frames", "keyframes", "culled", "live_keyframes", "landmarks", "live_landmarks",
           "landmark_rows", "rss_mib")


def rss_mib() -> float:
    """This process's resident set size (MiB)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def run_one(sequence: Path, settings: list[str], every: int) -> dict:
    """One replay in this process: the checkpoints (working set and RSS every ``every`` frames, and at the end) and
    the refined and online ATE RMSE (SE(3) Umeyama, association window 0.02 s; None where nothing can be aligned)."""
    from twohr.config import load_config
    from twohr.dataset import RGBDSequence
    from twohr.evaluation import evaluate
    from twohr_app.pipeline import run_sequence

    config = load_config(None, settings)
    data = RGBDSequence(sequence, camera=config.camera)
    checkpoints = []
    seen = 0

    def on_frame(frame, result, stats, schedule) -> None:
        nonlocal seen
        seen += 1
        if seen % every == 0:
            checkpoints.append({"frames": seen, **schedule.map.working_set(), "rss_mib": round(rss_mib(), 1)})

    result = run_sequence(data, config, progress=False, on_frame=on_frame)
    if seen % every:
        checkpoints.append({"frames": seen, **result.map.working_set(), "rss_mib": round(rss_mib(), 1)})
    gt = data.ground_truth(data.default_gt_extrinsic())

    def ate(trajectory) -> float | None:
        try:
            return evaluate(gt, trajectory)[0].ate.rmse
        except ValueError:  # nothing to align: a camera that only turns, or too few poses
            return None

    return {"checkpoints": checkpoints, "ate": ate(result.trajectory), "ate_online": ate(result.online),
            "fps": len(result.stats) / result.wall_s}


def _metres(value: float | None) -> str:
    return "n/a (no alignment: the camera only turned)" if value is None else f"{value:.4f} m"


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (rows_ax, rss_ax) = plt.subplots(1, 2, figsize=(10, 3.8))
    for name in dict.fromkeys(row["config"] for row in rows):
        mine = [row for row in rows if row["config"] == name]
        frames = [row["frames"] for row in mine]
        line, = rows_ax.plot(frames, [row["landmark_rows"] for row in mine], marker="o", label=f"{name}: rows")
        rows_ax.plot(frames, [row["landmarks"] for row in mine], ls=":", color=line.get_color(), label=f"{name}: made")
        rss_ax.plot(frames, [row["rss_mib"] for row in mine], marker="o", color=line.get_color(), label=name)
    rows_ax.set(xlabel="frames", ylabel="landmarks", title="landmark rows and landmarks made")
    rss_ax.set(xlabel="frames", ylabel="MiB", title="process RSS")
    for ax in (rows_ax, rss_ax):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m twohr_lab.tracking.long_session", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sequence", type=Path, required=True, help="TUM-layout RGB-D folder with ground truth")
    parser.add_argument("--every", type=int, default=560, help="frames between checkpoints (one pass of the dev "
                        "frames: 560)")
    parser.add_argument("--config", action="append", default=[], metavar="NAME=SETTINGS",
                        help="a configuration: a name and comma-separated key=value overrides (repeatable; "
                        "default: one run with the defaults)")
    parser.add_argument("--out", type=Path, default=Path("runs/long_session"), help="output folder")
    parser.add_argument("--one", help=argparse.SUPPRESS)  # internal: run one configuration, print JSON
    args = parser.parse_args(argv)
    if args.every < 1:
        parser.error("--every must be at least 1")
    if not (args.sequence / "groundtruth.txt").is_file():
        parser.error(f"{args.sequence} has no groundtruth.txt")
    if args.one is not None:
        print(json.dumps(run_one(args.sequence, [s for s in args.one.split(",") if s], args.every)))
        return 0
    configs = [c.partition("=")[::2] for c in args.config] or [("default", "")]
    args.out.mkdir(parents=True, exist_ok=True)
    rows, lines = [], []
    for name, settings in configs:
        print(f"{name}: replaying {args.sequence.name} ...", file=sys.stderr, flush=True)
        done = subprocess.run([sys.executable, "-m", "twohr_lab.tracking.long_session", "--sequence",
                               str(args.sequence), "--every", str(args.every), "--one", settings],
                              capture_output=True, text=True, env=os.environ | {"TQDM_DISABLE": "1"})
        if done.returncode != 0:
            print(done.stderr[-3000:], file=sys.stderr)
            return done.returncode
        run = json.loads(done.stdout.strip().splitlines()[-1])
        rows += [{"config": name, **checkpoint} for checkpoint in run["checkpoints"]]
        lines.append(f"- `{name}` (`{settings or 'defaults'}`): refined ATE {_metres(run['ate'])}, online "
                     f"{_metres(run['ate_online'])}, {run['fps']:.1f} FPS")
    with open(args.out / "rows.tsv", "w") as fh:
        fh.write("\t".join(COLUMNS) + "\n")
        fh.writelines("\t".join(str(row[c]) for c in COLUMNS) + "\n" for row in rows)
    table = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS),
             *("| " + " | ".join(str(row[c]) for c in COLUMNS) + " |" for row in rows)]
    (args.out / "long_session.md").write_text("\n".join([*table, "", *lines]) + "\n")
    plot(rows, args.out / "long_session.png")
    print("\n".join([*table, "", *lines]))
    print(f"wrote {args.out}/rows.tsv, long_session.md, long_session.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
