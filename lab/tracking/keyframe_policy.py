"""The keyframe-policy benchmark: ``twohr run`` on the dev frames and their variants, per configuration, on 2 cores,
on 1 core and beside one busy process, several runs each; a table of medians.

Runs are interleaved (run 1 of every cell, then run 2 ...) so that the machine's drift spreads over the cells::

    python -m twohr_lab.tracking.keyframe_policy --runs 3 --out runs/kfpolicy \\
        --config default= --config f32=detector.precision=f32

A ``--config`` is ``NAME=key=value[,key=value...]`` (``NAME=`` for the defaults). ``--twohr NAME=COMMAND`` runs another
build's ``twohr`` (say an older commit installed elsewhere) as one more configuration. Writes ``rows.tsv`` (one line per
run, as it goes), ``keyframe_policy.md`` (medians, with the command, commit and CPU), ``keyframe_policy.json`` and each
run's outputs.
"""

from __future__ import annotations

import argparse
import csv
import shlex
import statistics
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from twohr.paths import DEV_SEQUENCE

from ..stamp import write_study

CONDITIONS = {"2c": "2 cores", "1c": "1 core (`taskset -c 0`)", "busy": "2 cores beside one busy process"}
BUSY = [sys.executable, "-c", "while True: pass"]


@dataclass(frozen=True)
class Sequence:
    name: str
    path: str
    args: tuple[str, ...] = ()


def sequences(backwards_folder: str | None) -> dict[str, Sequence]:
    """The dev frames, their backwards variant (made by :mod:`.backwards`), the tail and every second frame."""
    found = {"dev": Sequence("dev", str(DEV_SEQUENCE)), "tail": Sequence("tail", str(DEV_SEQUENCE), ("--start", "280")),
             "step2": Sequence("step2", str(DEV_SEQUENCE), ("--step", "2"))}
    if backwards_folder:
        found["backwards"] = Sequence("backwards", backwards_folder)
    return found


def run_once(command: list[str], sequence: Sequence, settings: list[str], condition: str, out: Path) -> dict:
    """One ``twohr run``; returns its row (ATE refined and online, keyframes, FPS ...) from ``summary.json``."""
    import json

    cmd = [*command, "run", "--sequence", sequence.path, *sequence.args, "--out", str(out), "--quiet"]
    for setting in settings:
        cmd += ["--set", setting]
    if condition == "1c":
        cmd = ["taskset", "-c", "0", *cmd]
    busy = subprocess.Popen(BUSY) if condition == "busy" else None
    try:
        done = subprocess.run(cmd, capture_output=True, text=True)
    finally:
        if busy is not None:
            busy.kill()
            busy.wait()
    if done.returncode != 0:
        raise RuntimeError(f"{shlex.join(cmd)} failed:\n{done.stderr[-2000:]}")
    summary = json.loads((out / "summary.json").read_text())
    jobs, world = summary.get("keyframe_jobs", {}), summary.get("map", {})
    return {"ate": summary["ate"]["ate"]["rmse"], "ate_online": summary["ate_online"]["ate"]["rmse"],
            "keyframes": jobs.get("keyframes", ""), "live_keyframes": world.get("live_keyframes", ""),
            "jobs": jobs.get("count", ""), "shed": jobs.get("shed", ""), "fps": summary["fps"],
            "scale": summary.get("detector_input_scale", ""), "network": summary.get("detector_model", ""),
            "tracked": summary["tracked_percent"]}


def _spread(values: list) -> str:
    numbers = [v for v in values if v != ""]
    if not numbers:
        return ""
    low, high = min(numbers), max(numbers)
    return f"{low}" if low == high else f"{low}–{high}"


def table(rows: list[dict]) -> str:
    """Medians per (sequence, configuration, condition), runs listed."""
    lines = ["| sequence | config | condition | refined ATE, median (runs) | online ATE, median | online / refined | "
             "keyframes (live) | jobs shed | FPS, median | scale, network |", "|" + "---|" * 10]
    cells: dict[tuple, list[dict]] = {}
    for row in rows:
        cells.setdefault((row["sequence"], row["config"], row["condition"]), []).append(row)
    for (sequence, config, condition), runs in cells.items():
        ate = statistics.median(float(r["ate"]) for r in runs)
        online = statistics.median(float(r["ate_online"]) for r in runs)
        listed = ", ".join(f"{float(r['ate']):.4f}" for r in runs)
        keyframes = _spread([int(r["keyframes"]) for r in runs if r["keyframes"] != ""])
        live = _spread([int(r["live_keyframes"]) for r in runs if r["live_keyframes"] != ""])
        shed = _spread([int(r["shed"]) for r in runs if r["shed"] != ""])
        fps = statistics.median(float(r["fps"]) for r in runs)
        kinds = ", ".join(sorted({f"{r['scale']} {r['network']}".strip() for r in runs}))
        lines.append(f"| {sequence} | {config} | {CONDITIONS[condition]} | {ate:.4f} ({listed}) | {online:.4f} | "
                     f"{online / ate:.2f} | {keyframes}" + (f" ({live})" if live else "") +
                     f" | {shed} | {fps:.1f} | {kinds} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m twohr_lab.tracking.keyframe_policy",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=3, help="runs per cell (default 3)")
    parser.add_argument("--out", default="runs/kfpolicy", help="output folder")
    parser.add_argument("--sequences", default="dev,backwards,tail,step2", help="comma-separated: dev, backwards, "
                        "tail (--start 280), step2 (--step 2)")
    parser.add_argument("--backwards", default="runs/sequences/rgbd_bonn_crowd_dev_backwards", help="the backwards "
                        "variant's folder (python -m twohr_lab.tracking.backwards makes it)")
    parser.add_argument("--conditions", default="2c,1c,busy", help="comma-separated: 2c, 1c, busy")
    parser.add_argument("--config", action="append", default=None, metavar="NAME=SETTINGS",
                        help="a configuration: NAME=key=value[,key=value...] (NAME= for the defaults); repeatable")
    parser.add_argument("--twohr", action="append", default=[], metavar="NAME=COMMAND",
                        help="another build's twohr command, run with the defaults as configuration NAME")
    args = parser.parse_args(argv)
    argv = sys.argv[1:] if argv is None else argv
    known = sequences(args.backwards)
    wanted = [s.strip() for s in args.sequences.split(",") if s.strip()]
    missing = [s for s in wanted if s not in known or not Path(known[s].path).is_dir()]
    if missing:
        parser.error(f"no such sequence here: {', '.join(missing)} (the backwards variant: python -m "
                     "twohr_lab.tracking.backwards --sequence ../shared/data/rgbd_bonn_crowd_dev --out runs/sequences)")
    conditions = [c.strip() for c in args.conditions.split(",") if c.strip()]
    if unknown := [c for c in conditions if c not in CONDITIONS]:
        parser.error(f"unknown condition {', '.join(unknown)}: choose from {', '.join(CONDITIONS)}")
    configs: dict[str, tuple[list[str], list[str]]] = {}
    for item in args.config or ["default="]:
        name, _, settings = item.partition("=")
        configs[name] = ([sys.executable, "-m", "twohr_app.cli"], [s for s in settings.split(",") if s])
    for item in args.twohr:
        name, _, command = item.partition("=")
        configs[name] = (shlex.split(command), [])
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    fields = ["run", "sequence", "config", "condition", "ate", "ate_online", "keyframes", "live_keyframes", "jobs",
              "shed", "fps", "scale", "network", "tracked"]
    cells = [(s, n, c) for s in wanted for c in conditions for n in configs]
    from tqdm import tqdm

    with open(out / "rows.tsv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=fields, delimiter="\t")
        writer.writeheader()
        with tqdm(total=args.runs * len(cells), unit="run", desc="keyframe policy") as bar:
            for run in range(1, args.runs + 1):
                for sequence_name, config_name, condition in cells:
                    command, settings = configs[config_name]
                    run_out = out / f"{sequence_name}-{config_name}-{condition}-r{run}"
                    row = {"run": run, "sequence": sequence_name, "config": config_name, "condition": condition,
                           **run_once(command, known[sequence_name], settings, condition, run_out)}
                    rows.append(row)
                    writer.writerow(row)
                    fh.flush()
                    bar.update(1)
    from twohr.machine import machine

    markdown = f"CPU: {machine()['cpu_model']}\n\n{table(rows)}"
    write_study(out, "keyframe_policy", markdown, rows, argv, "python -m twohr_lab.tracking.keyframe_policy")
    print(markdown)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
