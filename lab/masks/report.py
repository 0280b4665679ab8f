"""Measurements of the yolo core on a sequence: per-frame statistics, pictures and timings.

A lab study: it composes the yolo core with the keypoint detector; the core itself stays in
``twohr_services.yolo`` (``core.py``, ``dynamics.py``, ``masks.py``).
"""

from __future__ import annotations

import csv
import json
import platform
import statistics
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from twohr.config import DetectorConfig, YoloConfig
from twohr.dataset import RGBDSequence
from twohr.features import Detections, Keypoints
from twohr_services.yolo.core import YoloDetector
from twohr_services.yolo.dynamics import LEVELS, DynamicsTable
from twohr_services.yolo.masks import DynamicMasker, box_mask, filter_keypoints, grow_boxes, region_mask

#: Drawing colours (RGB) per dynamics level; static classes are grey.
LEVEL_COLOURS = {"high": (230, 40, 40), "medium": (255, 150, 0), "low": (240, 220, 0), None: (160, 160, 160)}
KEPT_COLOUR = (40, 220, 40)
REMOVED_COLOUR = (255, 0, 255)
MASK_MODES = ("box", "depth")


@dataclass
class FrameStats:
    """What the yolo core did on one frame, for both mask modes."""

    index: int
    stamp: float
    fresh: bool
    detections: dict[str, int] = field(default_factory=dict)
    """count of detections per level (high, medium, low, static)."""
    dynamic: int = 0
    yolo_ms: float = 0.0
    mask_ms: dict[str, float] = field(default_factory=dict)
    area_pct: dict[str, float] = field(default_factory=dict)
    keypoints: int = 0
    removed_pct: dict[str, float] = field(default_factory=dict)

    def row(self) -> dict[str, object]:
        """A flat dict for a CSV row."""
        out: dict[str, object] = {"index": self.index, "stamp": f"{self.stamp:.6f}", "fresh": int(self.fresh)}
        out.update({f"det_{k}": v for k, v in self.detections.items()})
        out.update({"dynamic": self.dynamic, "yolo_ms": round(self.yolo_ms, 2), "keypoints": self.keypoints})
        for mode in MASK_MODES:
            out[f"area_{mode}_pct"] = round(self.area_pct.get(mode, float("nan")), 2)
            out[f"removed_{mode}_pct"] = round(self.removed_pct.get(mode, float("nan")), 2)
            out[f"mask_{mode}_ms"] = round(self.mask_ms.get(mode, float("nan")), 3)
        return out


def count_levels(detections: Detections, table: DynamicsTable) -> dict[str, int]:
    """Detections per dynamics level, with ``static`` for classes the table does not list."""
    counts = dict.fromkeys([*LEVELS, "static"], 0)
    for level in table.levels_of(detections):
        counts[level or "static"] += 1
    return counts


def evaluate_sequence(sequence: str | Path, conf: YoloConfig, detector_conf: DetectorConfig | None = None,
                      step: int = 5, start: int = 0, stop: int | None = None,
                      progress: bool = True) -> tuple[list[FrameStats], dict[str, object]]:
    """Run the masker over every ``step``-th frame and measure detections, mask area and removed keypoints.

    Both mask modes (box and depth) are computed from the same dynamic detections. With
    ``detector_conf`` = None no keypoints are detected (faster); otherwise 2HR/R2D2/ORB keypoints
    of each frame are split by both masks. ``conf.every_n`` counts *evaluated* frames."""
    seq = RGBDSequence(sequence)
    masker = DynamicMasker(conf)
    keypoint_detector = None
    if detector_conf is not None:
        from twohr_services.detector.core import build_detector

        keypoint_detector = build_detector(detector_conf)
    indices = range(start, len(seq) if stop is None else min(stop, len(seq)), step)
    stats: list[FrameStats] = []
    for frame in tqdm(seq.frames(start, stop, step), total=len(indices), desc="yolo eval", disable=not progress,
                      unit="frame"):
        t0 = time.perf_counter()
        regions = masker(frame.rgb, frame.depth)
        yolo_ms = (time.perf_counter() - t0) * 1e3
        shape = frame.rgb.shape[:2]
        item = FrameStats(frame.index, frame.stamp, regions.fresh, count_levels(regions.detections, masker.table),
                          len(regions.dynamic), yolo_ms)
        keypoints = keypoint_detector.detect(frame.rgb) if keypoint_detector is not None else None
        item.keypoints = len(keypoints) if keypoints is not None else 0
        for mode in MASK_MODES:
            t0 = time.perf_counter()
            mask = region_mask(regions.dynamic, shape, conf, frame.depth, mode)
            item.mask_ms[mode] = (time.perf_counter() - t0) * 1e3
            item.area_pct[mode] = 100.0 * float(mask.mean())
            if keypoints is not None and len(keypoints):
                item.removed_pct[mode] = 100.0 * float(filter_keypoints(keypoints, mask)[1].mean())
        stats.append(item)
    return stats, summarise(stats, conf, seq.skipped)


def _median(values: Sequence[float]) -> float:
    values = [v for v in values if np.isfinite(v)]
    return float(statistics.median(values)) if values else float("nan")


def _mean(values: Sequence[float]) -> float:
    values = [v for v in values if np.isfinite(v)]
    return float(np.mean(values)) if values else float("nan")


def summarise(stats: list[FrameStats], conf: YoloConfig, skipped: list[int] | None = None) -> dict[str, object]:
    """Sequence-level figures from per-frame statistics."""
    fresh = [s for s in stats if s.fresh]
    summary: dict[str, object] = {
        "model": conf.model, "frames": len(stats), "detector_runs": len(fresh), "skipped_frames": skipped or [],
        "remove_levels": list(conf.remove_levels), "every_n": conf.every_n, "box_margin": conf.box_margin,
        "detections_per_frame": {k: round(_mean([s.detections[k] for s in fresh]), 3)
                                 for k in [*LEVELS, "static"]},
        "frames_with_person_pct": round(100.0 * _mean([s.detections["high"] > 0 for s in fresh]), 1),
        "dynamic_per_frame": round(_mean([s.dynamic for s in stats]), 3),
        "yolo_ms_median_detector_frames": round(_median([s.yolo_ms for s in fresh]), 2),
        "yolo_ms_median_all_frames": round(_median([s.yolo_ms for s in stats]), 2),
        "keypoints_per_frame": round(_mean([s.keypoints for s in stats]), 1),
    }
    with_objects = [s for s in stats if s.dynamic > 0]
    summary["frames_with_dynamic_objects"] = len(with_objects)
    for mode in MASK_MODES:
        area = [s.area_pct[mode] for s in stats]
        removed_counts = [s.removed_pct.get(mode, float("nan")) * s.keypoints / 100 for s in stats]
        summary[mode] = {
            "mask_area_pct_mean": round(_mean(area), 2),
            "frames_mask_over_90pct": int(sum(a > 90 for a in area)),
            "keypoints_removed_pct_mean_of_frames": round(_mean([s.removed_pct.get(mode, np.nan) for s in stats]), 2),
            "keypoints_removed_pct_pooled": round(100 * np.nansum(removed_counts) / max(1, sum(
                s.keypoints for s in stats)), 2),
            "mask_ms_median": round(_median([s.mask_ms[mode] for s in stats]), 3),
            "with_objects": {
                "mask_area_pct_mean": round(_mean([s.area_pct[mode] for s in with_objects]), 2),
                "keypoints_removed_pct_mean_of_frames": round(
                    _mean([s.removed_pct.get(mode, np.nan) for s in with_objects]), 2),
            },
        }
    return summary


def write_eval(out_dir: str | Path, stats: list[FrameStats], summary: dict[str, object]) -> dict[str, Path]:
    """frames.csv, summary.json and eval.png (per-frame curves) in ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"frames": out / "frames.csv", "summary": out / "summary.json", "plot": out / "eval.png"}
    rows = [s.row() for s in stats]
    with open(paths["frames"], "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]) if rows else ["index"])
        writer.writeheader()
        writer.writerows(rows)
    paths["summary"].write_text(json.dumps(summary, indent=2) + "\n")
    plot_eval(paths["plot"], stats, str(summary.get("model", "")))
    return paths


def plot_eval(path: str | Path, stats: list[FrameStats], title: str = "") -> Path:
    """Detections per level, mask area and removed keypoints over the frames of a sequence."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    index = [s.index for s in stats]
    fig, axes = plt.subplots(3, 1, figsize=(12, 8), sharex=True)
    for level in [*LEVELS, "static"]:
        colour = np.array(LEVEL_COLOURS.get(level, LEVEL_COLOURS[None])) / 255
        axes[0].plot(index, [s.detections[level] for s in stats], ".-", lw=0.8, ms=3, color=colour, label=level)
    axes[0].set_ylabel("detections")
    axes[0].legend(loc="upper left", fontsize=8, ncol=4)
    for mode, style in zip(MASK_MODES, ["-", "--"], strict=True):
        axes[1].plot(index, [s.area_pct[mode] for s in stats], style, lw=1, label=f"{mode} mask")
        axes[2].plot(index, [s.removed_pct.get(mode, np.nan) for s in stats], style, lw=1, label=f"{mode} mask")
    axes[1].set_ylabel("mask area [% of image]")
    axes[2].set_ylabel("keypoints removed [%]")
    axes[2].set_xlabel("frame")
    for ax in axes:
        ax.grid(alpha=0.3)
    for ax in axes[1:]:
        ax.set_ylim(-2, 102)
        ax.legend(loc="upper left", fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)


def propagation_study(sequence: str | Path, conf: YoloConfig, every_n: Sequence[int] = (2, 3, 5),
                      growth: Sequence[float] = (0.0, 0.04, 0.08, 0.12), start: int = 0, stop: int | None = None,
                      progress: bool = True) -> list[dict[str, float]]:
    """How well masks propagated between detections cover the objects a fresh detection finds.

    The detector runs on every frame of [start, stop); for each ``every_n`` and ``growth`` the box
    mask propagated from the latest detection frame is compared with the box mask of that frame's
    own detections (the reference, itself only a detector's view). ``recall`` = covered reference
    pixels / reference pixels, pooled over the frames in between detections; ``inflation`` = masked
    pixels / reference pixels."""
    seq = RGBDSequence(sequence)
    masker = DynamicMasker(conf.model_copy(update={"every_n": 1}))
    stop = len(seq) if stop is None else min(stop, len(seq))
    dynamic, shape = [], None
    for frame in tqdm(seq.frames(start, stop), total=stop - start, desc="detect", disable=not progress):
        dynamic.append(masker(frame.rgb).dynamic)
        shape = frame.rgb.shape[:2]
    references = [box_mask(d, shape, conf.box_margin) for d in dynamic]
    rows = []
    for n in every_n:
        for g in growth:
            covered = total = masked = 0
            low_recall_frames = frames = 0
            for t in range(len(dynamic)):
                k = t % n
                if k == 0 or not references[t].any():
                    continue
                propagated = box_mask(grow_boxes(dynamic[t - k], k, g, shape), shape, conf.box_margin)
                hit = int((propagated & references[t]).sum())
                covered, total, masked = covered + hit, total + int(references[t].sum()), masked + int(propagated.sum())
                frames += 1
                low_recall_frames += hit < 0.95 * references[t].sum()
            rows.append({"every_n": n, "growth": g, "frames": frames,
                         "recall_pct": round(100 * covered / max(total, 1), 2),
                         "inflation": round(masked / max(total, 1), 3),
                         "frames_recall_below_95_pct": round(100 * low_recall_frames / max(frames, 1), 1)})
    return rows


# ----------------------------------------------------------------------------- pictures


def draw_regions(rgb: np.ndarray, mask: np.ndarray, detections: Detections, table: DynamicsTable,
                 keypoints: Keypoints | None = None, title: str = "") -> np.ndarray:
    """An RGB picture: the mask tinted red, every detection boxed in its level's colour with name and score,
    kept keypoints green and removed ones magenta; ``title`` goes in a black strip above the image."""
    canvas = rgb.copy()
    tint = np.array([255, 0, 0], np.float32)
    canvas[mask] = (0.55 * canvas[mask] + 0.45 * tint).astype(np.uint8)
    edges = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)).astype(bool)
    canvas[edges] = (255, 60, 60)
    for box, name, score, level in zip(detections.boxes, detections.names, detections.scores,
                                       table.levels_of(detections), strict=True):
        colour = LEVEL_COLOURS[level]
        x1, y1, x2, y2 = (int(round(v)) for v in box)
        cv2.rectangle(canvas, (x1, y1), (x2 - 1, y2 - 1), colour, 2)
        label = f"{name} {score:.2f}" + (f" [{level}]" if level else "")
        cv2.putText(canvas, label, (x1 + 3, max(12, y1 + 14)), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 3)
        cv2.putText(canvas, label, (x1 + 3, max(12, y1 + 14)), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1)
    if keypoints is not None and len(keypoints):
        _, removed = filter_keypoints(keypoints, mask)
        for (x, y), gone in zip(keypoints.xy, removed, strict=True):
            cv2.circle(canvas, (int(round(x)), int(round(y))), 2, REMOVED_COLOUR if gone else KEPT_COLOUR, -1)
    if title:
        strip = np.zeros((24, canvas.shape[1], 3), np.uint8)
        cv2.putText(strip, title, (5, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1)
        canvas = np.vstack([strip, canvas])
    return canvas


def visualise_frames(sequence: str | Path, frames: Sequence[int], out_dir: str | Path, conf: YoloConfig,
                     detector_conf: DetectorConfig | None = None, progress: bool = True,
                     scale: float = 1.0) -> list[Path]:
    """One PNG per frame: box mask (left) and depth-refined mask (right) with boxes and kept/removed keypoints,
    resized by ``scale``. Each frame is detected afresh (``every_n`` does not apply to isolated frames)."""
    from twohr.errors import DatasetError

    seq = RGBDSequence(sequence)
    bad = [i for i in frames if not 0 <= i < len(seq)]
    if bad:
        raise DatasetError(f"frame(s) {bad} out of range: {seq.root} has frames 0..{len(seq) - 1}")
    masker = DynamicMasker(conf.model_copy(update={"every_n": 1}))
    keypoint_detector = None
    if detector_conf is not None:
        from twohr_services.detector.core import build_detector

        keypoint_detector = build_detector(detector_conf)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for index in tqdm(frames, desc="yolo viz", disable=not progress, unit="frame"):
        frame = seq.read(index)
        regions = masker(frame.rgb, frame.depth)
        keypoints = keypoint_detector.detect(frame.rgb) if keypoint_detector is not None else None
        panels = []
        for mode in MASK_MODES:
            mask = region_mask(regions.dynamic, frame.rgb.shape[:2], conf, frame.depth, mode)
            removed = filter_keypoints(keypoints, mask)[1] if keypoints is not None else np.zeros(0, bool)
            title = (f"frame {index}  {mode} mask {100 * mask.mean():.0f}% of image"
                     + (f"  removed {removed.sum()}/{len(removed)} keypoints" if keypoints is not None else ""))
            panels.append(draw_regions(frame.rgb, mask, regions.detections, masker.table, keypoints, title))
        path = out / f"frame_{index:04d}.png"
        picture = np.hstack(panels)
        if scale != 1.0:
            picture = cv2.resize(picture, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(path), cv2.cvtColor(picture, cv2.COLOR_RGB2BGR))
        paths.append(path)
    return paths


# ----------------------------------------------------------------------------- timings


def _benchmark_images(sequence: str | Path | None, frames: Sequence[int]) -> list[tuple[np.ndarray, np.ndarray]]:
    if sequence is not None:
        seq = RGBDSequence(sequence)
        picked = [i for i in frames if 0 <= i < len(seq)] or [0]
        return [(f.rgb, f.depth) for f in (seq.read(i) for i in picked)]
    from twohr.synthetic import SyntheticScene, SyntheticSpec, camera_path

    spec = SyntheticSpec(frames=2, width=640, height=480)
    rgb, depth, _ = SyntheticScene(spec).render(camera_path(spec).poses[0], 0.0)
    return [(rgb, depth.astype(np.float32))]


def benchmark_yolo(sequence: str | Path | None = None,
                   models: Sequence[str] = ("yolov8n_320", "yolov8n", "yolov5n_320", "yolov5n"),
                   runs: int = 10, threads: int = 2, frames: Sequence[int] = (320, 445, 100),
                   progress: bool = False) -> dict[str, object]:
    """Milliseconds per frame of each YOLO model (median of ``runs`` rounds over ``frames``), on 640x480 frames.

    ``detect_ms`` is the whole :meth:`YoloDetector.detect` (letterbox, network, decode, NMS);
    the in-run baseline ``session_ms`` is the bare onnxruntime call on the same prepared input,
    so ``detect_over_session`` is the cost of our pre- and post-processing. Rounds interleave the
    models so that load from other processes hits them alike. Mask timings use the first frame's
    person detections of the first model. Without ``sequence`` a synthetic 640x480 frame is used."""
    images = _benchmark_images(sequence, frames)
    detectors = {m: YoloDetector(YoloConfig(model=m, threads=threads)) for m in models}
    timings: dict[str, dict[str, list[float]]] = {m: {"detect": [], "session": []} for m in models}
    for detector in detectors.values():  # warm-up: first runs allocate
        for rgb, _ in images:
            detector.detect(rgb)
    for _ in tqdm(range(runs), desc="yolo bench", disable=not progress):
        for name, detector in detectors.items():
            for rgb, _ in images:
                t0 = time.perf_counter()
                detector.detect(rgb)
                timings[name]["detect"].append((time.perf_counter() - t0) * 1e3)
                feed = {detector.input_name: detector._tensor}
                t0 = time.perf_counter()
                detector.network(feed)
                timings[name]["session"].append((time.perf_counter() - t0) * 1e3)
    result: dict[str, object] = {"image_size": list(images[0][0].shape[1::-1]), "threads": threads, "runs": runs,
                                 "frames_per_run": len(images), "machine": platform.processor() or platform.machine(),
                                 "models": {}}
    baseline = statistics.median(timings[models[0]]["detect"])
    for name in models:
        detect_ms = statistics.median(timings[name]["detect"])
        session_ms = statistics.median(timings[name]["session"])
        result["models"][name] = {
            "input": detectors[name].input_size, "kind": detectors[name].kind,
            "detect_ms": round(detect_ms, 2), "session_ms": round(session_ms, 2),
            "detect_over_session": round(detect_ms / session_ms, 3),
            f"detect_over_{models[0]}": round(detect_ms / baseline, 3),
        }
    conf = YoloConfig(model=models[0])
    rgb, depth = images[0]
    people = detectors[models[0]].detect(rgb)
    people = DynamicsTable(high=["person"]).select(people, ["high"])
    mask_times: dict[str, list[float]] = {mode: [] for mode in MASK_MODES}
    for _ in range(runs):
        for mode in MASK_MODES:
            t0 = time.perf_counter()
            region_mask(people, rgb.shape[:2], conf, depth, mode)
            mask_times[mode].append((time.perf_counter() - t0) * 1e3)
    result["masks"] = {"objects": len(people), **{f"{mode}_ms": round(statistics.median(t), 3)
                                                   for mode, t in mask_times.items()}}
    result["masks"].update({f"{mode}_over_{models[0]}_detect": round(result["masks"][f"{mode}_ms"] / baseline, 4)
                            for mode in MASK_MODES})
    return result


def format_benchmark(result: dict[str, object]) -> str:
    """A small markdown table of :func:`benchmark_yolo`'s result."""
    models = result["models"]
    base = next(iter(models))
    lines = [f"YOLO on {result['image_size'][0]}x{result['image_size'][1]} frames, {result['threads']} threads, "
             f"median of {result['runs']} x {result['frames_per_run']} runs",
             "", f"| model | input | detect ms | bare session ms | detect / session | detect / {base} |",
             "|---|---|---|---|---|---|"]
    for name, m in models.items():
        lines.append(f"| {name} | {m['input']} | {m['detect_ms']:.2f} | {m['session_ms']:.2f} | "
                     f"{m['detect_over_session']:.2f} | {m[f'detect_over_{base}']:.2f} |")
    masks = result["masks"]
    lines += ["", f"masks for {masks['objects']} person box(es): box {masks['box_ms']:.2f} ms "
              f"({masks[f'box_over_{base}_detect']:.3f} x {base} detect), depth-refined {masks['depth_ms']:.2f} ms "
              f"({masks[f'depth_over_{base}_detect']:.3f} x)"]
    return "\n".join(lines)

