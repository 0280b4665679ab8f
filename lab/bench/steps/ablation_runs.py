"""The ablation table: ATE, S.D., % tracked and ms/frame of each named preset on the same tracker."""

from __future__ import annotations

import numpy as np

from twohr.config import PRESETS, PipelineConfig, load_config, merge_overrides
from twohr.evaluation import evaluate
from twohr_app.pipeline import run_sequence

from .front_cache import FrontCache

#: The ablation variants: the table's row -> config overrides on top of the user's config. They are the product's
#: named presets (``twohr run --preset NAME`` runs one row alone).
ABLATIONS: dict[str, dict[str, object]] = {preset.label: preset.overrides for preset in PRESETS.values()}


def ablations(sequence, base: PipelineConfig, variants: dict[str, dict] | None = None, stop: int | None = None,
              repeats: int = 3, progress: bool = True) -> list[dict]:
    """ATE RMSE, S.D., % of frames tracked and ms/frame for each variant on one sequence.

    The networks are deterministic, so each front end runs once; the tracker runs twice, and where
    the two runs differ it runs ``repeats`` times and the median is reported."""
    variants = variants or ABLATIONS
    stop = len(sequence) if stop is None else min(stop, len(sequence))
    gt = sequence.ground_truth(sequence.default_gt_extrinsic())
    cache = FrontCache()
    rows = []
    for name, overrides in variants.items():
        config = load_config(None, merge_overrides(base.model_dump(mode="json"), overrides))
        config.pipeline.mode = "every_frame"  # the variants share cached front-end outputs of every frame
        fronts = cache.outputs(sequence, config, stop, progress)

        def once(config=config, fronts=fronts):
            run = run_sequence(sequence, config, stop=stop, progress=False, front_cache=fronts)
            for row in run.stats:  # the networks ran once, into the cache: their time is the cached one
                front = fronts[row.index]
                row.ms_detector, row.ms_yolo = front.ms_detector, front.ms_yolo
                row.ms_total += front.ms_detector + front.ms_yolo
            report, _ = evaluate(gt, run.trajectory, gt_extrinsic=sequence.default_gt_extrinsic())
            return report.ate.rmse, report.ate.std, run

        runs = [once(), once()]
        deterministic = np.allclose(runs[0][2].trajectory.poses, runs[1][2].trajectory.poses)
        if not deterministic:
            runs += [once() for _ in range(repeats - 2)]
        rmse = [r[0] for r in runs]
        pick = runs[int(np.argsort(rmse)[len(rmse) // 2])]
        run = pick[2]
        rows.append({
            "variant": name, "ate_rmse": round(float(np.median(rmse)), 4), "ate_std": round(pick[1], 4),
            "runs": 1 if deterministic else len(runs), "deterministic": deterministic,
            "tracked_percent": round(run.tracked_percent, 1),
            "ms_per_frame": round(float(np.median([s.ms_total for s in run.stats])), 1),
            "ms_detector": round(float(np.median([s.ms_detector for s in run.stats])), 1),
            "ms_yolo": round(float(np.median([s.ms_yolo for s in run.stats])), 1),
            "ms_tracker": round(float(np.median([s.ms_tracker for s in run.stats])), 1),
        })
    return rows


def static_camera_row(sequence) -> dict:
    """The sanity baseline: a camera that never moves."""
    from twohr.evaluation import static_trajectory

    report, _ = evaluate(sequence.ground_truth(sequence.default_gt_extrinsic()), static_trajectory(sequence.stamps),
                         gt_extrinsic=sequence.default_gt_extrinsic())
    return {"variant": "static camera (sanity)", "ate_rmse": round(report.ate.rmse, 4),
            "ate_std": round(report.ate.std, 4), "runs": 1, "deterministic": True, "tracked_percent": 100.0,
            "ms_per_frame": 0.0}


def format_table(rows: list[dict]) -> str:
    lines = ["| variant | ATE RMSE (m) | S.D. (m) | tracked % | ms/frame | runs |", "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['variant']} | {r['ate_rmse']:.4f} | {r['ate_std']:.4f} | {r['tracked_percent']:.1f} | "
                     f"{r['ms_per_frame']:.0f} | {r['runs']}{'' if r['deterministic'] else ' (median)'} |")
    return "\n".join(lines)
