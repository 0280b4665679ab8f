"""Development run of the tracker on a real RGB-D sequence: detector -> person-box mask -> tracker -> ATE.

The slow part (keypoints and person boxes) is computed once and cached in an .npz (default under
/tmp), so the tracker can be iterated on quickly::

    .venv/bin/python -m twohr_services.tracker.dev_run --sequence ../shared/data/rgbd_bonn_crowd_dev
    .venv/bin/python -m twohr_services.tracker.dev_run --features orb --no-mask      # the ORB ablation
    .venv/bin/python -m twohr_services.tracker.dev_run --set local_map_keyframes=4 --set min_inliers=20

It writes the estimate (TUM), a JSON report and a plot into ``--out``. This is a development tool:
the product entry point is ``twohr run`` (composed by the pipeline).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from twohr.config import DetectorConfig, TrackerConfig, load_config
from twohr.errors import TwohrError
from twohr.features import Keypoints, Matches

log = logging.getLogger("twohr.tracker.dev_run")

REPO = Path(__file__).resolve().parents[2]
DEFAULT_SEQUENCE = REPO.parent / "shared" / "data" / "rgbd_bonn_crowd_dev"
RESULTS = Path(__file__).resolve().parent / "results"


def person_box_detector():
    """Person boxes (N, 5: x1 y1 x2 y2 score) from the yolo core.

    Boxes are kept down to score 0.1 in the cache; ``--box-score`` picks at run time."""
    from twohr.config import YoloConfig
    from twohr_services.yolo.core import YoloDetector

    detector = YoloDetector(YoloConfig(conf_threshold=0.1))

    def detect(rgb: np.ndarray) -> np.ndarray:
        found = detector.detect(rgb)
        person = np.array([name == "person" for name in found.names], bool)
        return np.column_stack([found.boxes[person], found.scores[person]]).astype(np.float32).reshape(-1, 5)

    return detect


# ----------------------------------------------------------------------------- cache


def cache_path(cache_dir: Path, sequence, features: str, frames: int, step: int) -> Path:
    return cache_dir / f"{sequence.name}_{features}_n{frames}_s{step}.npz"


def build_cache(sequence, features: str, frame_indices: list[int], path: Path) -> Path:
    """Detect keypoints and person boxes on the chosen frames; save all of it in one .npz."""
    from tqdm import tqdm

    from twohr_services.detector.core import build_detector

    detector = build_detector(DetectorConfig(features=features))
    people = person_box_detector()
    xy, desc, scores, boxes, kp_count, box_count = [], [], [], [], [], []
    timings = []
    for index in tqdm(frame_indices, desc=f"detect {features}", unit="frame"):
        frame = sequence.read(index)
        start = time.perf_counter()
        kps = detector.detect(frame.rgb)
        timings.append(time.perf_counter() - start)
        xy.append(kps.xy)
        desc.append(kps.descriptors.astype(np.float16) if not kps.binary else kps.descriptors)
        scores.append(kps.scores)
        kp_count.append(len(kps))
        found = people(frame.rgb)
        boxes.append(found)
        box_count.append(len(found))
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, frames=np.asarray(frame_indices), xy=np.concatenate(xy), descriptors=np.concatenate(desc),
             scores=np.concatenate(scores), kp_count=np.asarray(kp_count), boxes=np.concatenate(boxes),
             box_count=np.asarray(box_count), detect_seconds=np.asarray(timings))
    return path


class CachedFrames:
    """Per-frame keypoints and person boxes read back from a cache file."""

    def __init__(self, path: Path) -> None:
        data = np.load(path)
        self._all_frames = data["frames"]
        self.frames = self._all_frames
        self._positions = np.arange(len(self.frames))
        self._xy, self._desc, self._scores = data["xy"], data["descriptors"], data["scores"]
        self._boxes = data["boxes"]
        self._kp_start = np.concatenate([[0], np.cumsum(data["kp_count"])])
        self._box_start = np.concatenate([[0], np.cumsum(data["box_count"])])
        self.detect_seconds = data["detect_seconds"]

    def select(self, positions: np.ndarray) -> None:
        """Keep only these entries (positions into the cached frames)."""
        self._positions = positions
        self.frames = self._all_frames[positions]

    def keypoints(self, k: int) -> Keypoints:
        k = self._positions[k]
        a, b = self._kp_start[k], self._kp_start[k + 1]
        desc = self._desc[a:b]
        if desc.dtype == np.float16:
            desc = desc.astype(np.float32)
            desc /= np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
        return Keypoints(self._xy[a:b], desc, self._scores[a:b])

    def person_boxes(self, k: int, min_score: float) -> np.ndarray:
        k = self._positions[k]
        boxes = self._boxes[self._box_start[k]:self._box_start[k + 1]]
        return boxes[boxes[:, 4] >= min_score, :4]


def outside_boxes(xy: np.ndarray, boxes: np.ndarray, margin: float) -> np.ndarray:
    """Boolean mask of keypoints outside every box dilated by ``margin`` pixels."""
    if len(boxes) == 0:
        return np.ones(len(xy), bool)
    lo = boxes[None, :, :2] - margin
    hi = boxes[None, :, 2:4] + margin
    inside = np.all((xy[:, None, :] >= lo) & (xy[:, None, :] <= hi), axis=2).any(axis=1)
    return ~inside


# ----------------------------------------------------------------------------- run


def mutual_nn_match(desc_a: np.ndarray, desc_b: np.ndarray) -> Matches:
    from twohr_services.matcher.core import mutual_nn

    return mutual_nn(desc_a, desc_b)


def parse_value(raw: str):
    """A command-line value as JSON where it parses (numbers, true/false), else the string."""
    try:
        return json.loads(raw)
    except json.JSONDecodeError:
        return raw


def tracker_config(settings: list[str], overrides: dict | None = None) -> TrackerConfig:
    """The tracker section from ``key=value`` strings, validated like ``twohr`` config overrides."""
    items = [f"tracker.{item}" for item in settings]
    items += [f"tracker.{key}={json.dumps(value)}" for key, value in (overrides or {}).items()]
    return load_config(overrides=items).tracker


def load_inputs(args: argparse.Namespace):
    """The sequence and its cached keypoints and person boxes. The cache holds every ``step``-th frame of the
    whole sequence (built on first use); ``--start`` and ``--frames`` pick from it."""
    from twohr.dataset import RGBDSequence

    sequence = RGBDSequence(args.sequence)
    path = cache_path(Path(args.cache_dir), sequence, args.features, len(sequence), args.step)
    every_frame = cache_path(Path(args.cache_dir), sequence, args.features, len(sequence), 1)
    if every_frame.is_file() and not args.rebuild_cache:
        path = every_frame  # a cache of every frame serves any step
    elif not path.is_file() or args.rebuild_cache:
        log.info("building the keypoint cache %s (once)", path)
        build_cache(sequence, args.features, list(range(0, len(sequence), args.step)), path)
    cached = CachedFrames(path)
    stop = args.frames or len(sequence)
    frames = cached.frames
    cached.select(np.flatnonzero((frames >= args.start) & (frames < stop) & ((frames - args.start) % args.step == 0)))
    return sequence, cached


def track_sequence(sequence, cached: CachedFrames, conf: TrackerConfig, args: argparse.Namespace):
    """Run the tracker over the cached frames; returns (per-frame results, tracker, stamps)."""
    from tqdm import tqdm

    from twohr_services.tracker.core import Tracker

    tracker = Tracker(sequence.camera, conf, match=mutual_nn_match)
    results, stamps = [], []
    for k in tqdm(range(len(cached.frames)), desc="track", unit="frame", disable=args.quiet):
        frame = sequence.read(int(cached.frames[k]))
        kps = cached.keypoints(k)
        if not args.no_mask:
            kps = kps.subset(outside_boxes(kps.xy, cached.person_boxes(k, args.box_score), args.box_margin))
        results.append(tracker.track(frame.stamp, kps, frame.depth))
        stamps.append(frame.stamp)
    return results, tracker, np.asarray(stamps)


def ate(sequence, estimate, extrinsic: str):
    from twohr.evaluation import evaluate

    return evaluate(sequence.ground_truth(extrinsic), estimate, gt_extrinsic=extrinsic)


def run(args: argparse.Namespace, overrides: dict | None = None, write: bool = True) -> dict:
    """One tracker run over the cached frames; writes estimate, report and plots into ``args.out``."""
    from twohr.plots import plot_trajectories
    from twohr.trajectory import Trajectory, write_tum

    sequence, cached = load_inputs(args)
    conf = tracker_config(args.set, overrides)
    results, tracker, stamps = track_sequence(sequence, cached, conf, args)
    online = Trajectory(stamps, np.asarray([r.pose for r in results]))
    refined = tracker.trajectory()
    extrinsic = sequence.default_gt_extrinsic()
    report, arrays = ate(sequence, refined, extrinsic)
    online_report, _ = ate(sequence, online, extrinsic)
    raw_report, _ = ate(sequence, refined, "none")
    statuses = [r.status for r in results]
    timing_keys = sorted({key for r in results for key in r.timings})
    summary = {
        "features": args.features,
        "mask": not args.no_mask,
        "frames": len(results),
        "step": args.step,
        "ate_rmse": report.ate.rmse,
        "ate_rmse_online": online_report.ate.rmse,
        "ate_rmse_raw_gt": raw_report.ate.rmse,
        "rpe_frame_rmse": report.rpe_frame.rmse,
        "rpe_1s_rmse": report.rpe_1s.rmse,
        "status_counts": {s: statuses.count(s) for s in sorted(set(statuses))},
        "keyframes": len(tracker.keyframes),
        "landmarks": tracker.map.num_good,
        "median_ms": {key: float(np.median([r.timings[key] for r in results if key in r.timings]))
                      for key in timing_keys},
        "config": conf.model_dump(),
        "untracked_frames": [int(cached.frames[k]) for k, r in enumerate(results) if not r.tracked],
    }
    if write:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        write_tum(out / "estimate.txt", refined, header=f"twohr tracker dev_run {args.features}")
        write_tum(out / "estimate_online.txt", online, header=f"twohr tracker dev_run {args.features}, online")
        (out / "report.json").write_text(json.dumps(_finite(summary), indent=2))
        if not args.no_plot:
            plot_trajectories(out / "trajectory.png", arrays["gt"], arrays["est"], arrays["ate"],
                              title=f"tracker dev_run: {args.features}{'' if args.no_mask else ' + person boxes'}; "
                              f"keyframe-refined trajectory ATE {report.ate.rmse:.3f} m (online poses: "
                              f"{online_report.ate.rmse:.3f} m)")
            plot_health(out / "health.png", results, cached.frames)
    return summary


def sweep(args: argparse.Namespace) -> str:
    """One-at-a-time sensitivity: ATE for each listed value of each swept field, the others at their defaults.
    The default run counts towards every field's median."""
    header = ["| parameter | value | ATE online (m) | ATE refined (m) | untracked frames | keyframes | ms/frame |",
              "|---|---|---|---|---|---|---|"]

    def row(key: str, value: str, summary: dict) -> str:
        untracked = len(summary["untracked_frames"])
        return (f"| {key} | {value} | {summary['ate_rmse_online']:.4f} | {summary['ate_rmse']:.4f} | {untracked} | "
                f"{summary['keyframes']} | {summary['median_ms']['total']:.0f} |")

    default = run(args, write=False)
    rows = header + [row("(all defaults)", "", default)]
    print(rows[-1], flush=True)
    online_all, refined_all = [default["ate_rmse_online"]], [default["ate_rmse"]]
    for item in args.sweep:
        key, _, values = item.partition("=")
        online, refined = [default["ate_rmse_online"]], [default["ate_rmse"]]
        rows.append(row(key, f"{default['config'][key]} (default)", default))
        for raw in values.split(","):
            summary = run(args, overrides={key: parse_value(raw)}, write=False)
            online.append(summary["ate_rmse_online"])
            refined.append(summary["ate_rmse"])
            rows.append(row(key, raw, summary))
            print(rows[-1], flush=True)
        rows.append(f"| {key} | median | {np.median(online):.4f} | {np.median(refined):.4f} | | | |")
        online_all += online[1:]
        refined_all += refined[1:]
    rows.append(f"| all settings | median (min-max) | {np.median(online_all):.4f} ({min(online_all):.4f}-"
                f"{max(online_all):.4f}) | {np.median(refined_all):.4f} ({min(refined_all):.4f}-"
                f"{max(refined_all):.4f}) | | | |")
    table = "\n".join(rows) + "\n"
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "sensitivity.md").write_text(table)
    return table


def _finite(value):
    """NaN -> None, so the JSON report stays standard JSON."""
    if isinstance(value, dict):
        return {key: _finite(v) for key, v in value.items()}
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def plot_health(path: Path, results, frame_indices) -> None:
    """Inliers, matches and status over the frames: where tracking struggles."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(12, 4))
    ax.plot(frame_indices, [r.num_keypoints for r in results], lw=0.8, label="keypoints")
    ax.plot(frame_indices, [r.num_matches for r in results], lw=0.8, label="matches")
    ax.plot(frame_indices, [r.num_inliers for r in results], lw=0.8, label="inliers")
    bad = [i for i, r in zip(frame_indices, results, strict=True) if r.status not in ("init", "tracking")]
    ax.scatter(bad, np.zeros(len(bad)), marker="|", color="red", s=80, label="lost / coasting / relocalised")
    kf = [i for i, r in zip(frame_indices, results, strict=True) if r.is_keyframe]
    ax.scatter(kf, np.full(len(kf), -20), marker="|", color="k", s=40, label="keyframe")
    ax.set_xlabel("frame")
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description="Run the R2D2/2HR (or ORB) detector, a YOLOv8 person-box mask, mutual-NN matching and the "
        "tracker over an RGB-D sequence; write the trajectory, ATE report and plots. Keypoints and boxes are "
        "computed once per (sequence, features, step) and cached; later runs only track.")
    parser.add_argument("--sequence", default=str(DEFAULT_SEQUENCE), help="TUM-layout RGB-D folder")
    parser.add_argument("--features", choices=["2hr", "r2d2", "orb"], default="2hr",
                        help="keypoints: 2hr (R2D2 + K-means filter, default), raw r2d2, or the orb baseline")
    parser.add_argument("--start", type=int, default=0, help="first frame index to track")
    parser.add_argument("--frames", type=int, default=0, help="stop before this frame index (0 = the end)")
    parser.add_argument("--step", type=int, default=1, help="use every n-th frame")
    parser.add_argument("--no-mask", action="store_true", help="keep keypoints on people")
    parser.add_argument("--box-score", type=float, default=0.25, help="person box confidence threshold")
    parser.add_argument("--box-margin", type=float, default=8.0, help="dilate person boxes by this many pixels")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a TrackerConfig field (repeatable)")
    parser.add_argument("--sweep", action="append", default=[], metavar="KEY=V1,V2,...",
                        help="sensitivity table: rerun with each value of KEY (repeatable), write sensitivity.md")
    parser.add_argument("--cache-dir", default="/tmp/twohr_tracker_cache", help="keypoint and box cache")
    parser.add_argument("--rebuild-cache", action="store_true", help="detect again even if cached")
    parser.add_argument("--out", default=str(RESULTS / "dev_run"), help="where to write estimate, report, plots")
    parser.add_argument("--no-plot", action="store_true")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        if args.sweep:
            print(sweep(args))
            return 0
        summary = run(args)
    except (TwohrError, ValueError) as exc:
        print(f"dev_run: error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(_finite({k: v for k, v in summary.items() if k not in ("config", "untracked_frames")}), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
