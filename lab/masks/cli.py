"""``twohr yolo``: detect dynamic objects, measure the masks on a sequence, draw them, time them.

A thin shell over the yolo core (:mod:`twohr_services.yolo`) and :mod:`twohr_lab.masks.report`; heavy modules are
imported inside the handlers so that ``twohr --help`` stays fast.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from twohr.errors import ConfigError, DatasetError, validation_problems
from twohr.paths import DEV_SEQUENCE

from ..stamp import provenance, write_stamp

KEYPOINT_CHOICES = ["2hr", "r2d2", "orb", "none"]


def _frame_list(text: str) -> list[int]:
    try:
        frames = [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        message = f"expected comma-separated frame numbers like 100,320,445, got {text!r}"
        raise argparse.ArgumentTypeError(message) from None
    if not frames:
        raise argparse.ArgumentTypeError("no frame numbers given")
    return frames


def _yolo_conf(args: argparse.Namespace):
    """The ``yolo`` config section: defaults, then --config, then --set, then the explicit flags."""
    from pydantic import ValidationError

    from twohr.config import YoloConfig, load_config

    conf = load_config(args.config, args.set).yolo
    flags = {"model": args.model, "mask": getattr(args, "mask", None), "every_n": getattr(args, "every_n", None),
             "dynamics_table": getattr(args, "table", None), "remove_levels": getattr(args, "levels", None)}
    updates = {k: v for k, v in flags.items() if v is not None}
    try:
        return YoloConfig.model_validate({**conf.model_dump(), **updates})
    except ValidationError as exc:
        raise ConfigError(f"invalid yolo option: {validation_problems(exc)}") from None


def _detector_conf(args: argparse.Namespace):
    from twohr.config import load_config

    if args.keypoints == "none":
        return None
    return load_config(args.config, args.set).detector.model_copy(update={"features": args.keypoints})


def _eval(args: argparse.Namespace) -> int:
    from .report import evaluate_sequence, write_eval

    if args.step < 1:
        raise ConfigError("--step must be at least 1")
    conf = _yolo_conf(args)
    stop = None if args.frames is None else args.start + args.frames * args.step
    stats, summary = evaluate_sequence(args.sequence, conf, _detector_conf(args), step=args.step,
                                       start=args.start, stop=stop)
    if not stats:
        raise DatasetError(f"no frames evaluated in {args.sequence} (start {args.start}, frames {args.frames})")
    summary["keypoints"] = args.keypoints
    summary["sequence"] = str(args.sequence)
    summary["step"] = args.step
    paths = write_eval(args.out, stats, summary)
    paths["stamp"] = write_stamp(args.out, args.argv)
    print(json.dumps(summary, indent=2))
    for name, path in paths.items():
        print(f"{name}: {path}")
    return 0


def _viz(args: argparse.Namespace) -> int:
    from .report import visualise_frames

    if not 0.05 <= args.scale <= 4:
        raise ConfigError("--scale must be between 0.05 and 4")
    paths = visualise_frames(args.sequence, args.indices, args.out, _yolo_conf(args), _detector_conf(args),
                             scale=args.scale)
    for path in paths:
        print(path)
    return 0


def _bench(args: argparse.Namespace) -> int:
    from .report import benchmark_yolo, format_benchmark

    if args.runs < 1:
        raise ConfigError("--runs must be at least 1")
    sequence = args.sequence if args.sequence and Path(args.sequence).exists() else None
    if args.sequence and sequence is None and args.sequence != DEV_SEQUENCE:
        raise DatasetError(f"sequence folder not found: {args.sequence}")
    result = benchmark_yolo(sequence, models=args.models, runs=args.runs, threads=args.threads, progress=True)
    result["sequence"] = str(sequence) if sequence else "synthetic 640x480 frame"
    print(format_benchmark(result))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({**result, "provenance": provenance(args.argv)}, indent=2) + "\n")
        print(f"json: {args.json}")
    return 0


def _propagation(args: argparse.Namespace) -> int:
    from .report import propagation_study

    conf = _yolo_conf(args)
    stop = None if args.frames is None else args.start + args.frames
    rows = propagation_study(args.sequence, conf, args.intervals, args.growth, args.start, stop)
    lines = ["| every_n | growth | frames | recall % | inflation | frames with recall < 95 % |",
             "|---|---|---|---|---|---|"]
    lines += [f"| {r['every_n']} | {r['growth']:.2f} | {r['frames']} | {r['recall_pct']:.2f} | {r['inflation']:.3f} | "
              f"{r['frames_recall_below_95_pct']:.1f} |" for r in rows]
    print("\n".join(lines))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"model": conf.model, "start": args.start, "stop": stop,
                                               "box_margin": conf.box_margin, "rows": rows,
                                               "provenance": provenance(args.argv)}, indent=2) + "\n")
        print(f"json: {args.json}")
    return 0


def _detect(args: argparse.Namespace) -> int:
    import cv2

    from twohr_services.yolo.core import YoloDetector
    from twohr_services.yolo.dynamics import load_dynamics_table

    path = Path(args.image)
    if not path.is_file():
        raise DatasetError(f"image not found: {path}")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise DatasetError(f"not a readable image: {path}")
    conf = _yolo_conf(args)
    table = load_dynamics_table(conf.dynamics_table)
    detections = YoloDetector(conf).detect(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    for box, name, score, level in zip(detections.boxes, detections.names, detections.scores,
                                       table.levels_of(detections), strict=True):
        x1, y1, x2, y2 = (round(float(v), 1) for v in box)
        print(f"{name:14} {score:.2f}  {level or 'static':6}  box {x1} {y1} {x2} {y2}")
    print(f"{len(detections)} detection(s) with {conf.model}")
    return 0


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", help="yolov8n_320 (default), yolov8n, yolov5n_320 or yolov5n (see `twohr models list`)")
    p.add_argument("--config", help="pipeline config YAML; its `yolo` and `detector` sections apply")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value, e.g. --set yolo.box_margin=12 (repeatable)")


def _mask_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mask", choices=["box", "depth"],
                   help="the mask the masker uses (both are always measured/drawn; default box)")
    p.add_argument("--levels", type=lambda s: [x.strip() for x in s.split(",") if x.strip()],
                   help="dynamics levels to remove, comma-separated: high,medium,low (default high)")
    p.add_argument("--table", help="dynamics table YAML (default: the paper's table, services/yolo/dynamics.yaml)")


def register(sub: argparse._SubParsersAction) -> None:
    yolo = sub.add_parser(
        "yolo", help="dynamic-object detection and keypoint masking (YOLO + dynamics table)",
        description="YOLOv8n/YOLOv5n detections, the paper's dynamics table (high: person; medium: chair, book; "
        "low: dining table, tv) and the masks that remove keypoints on moving objects.",
    )
    actions = yolo.add_subparsers(dest="yolo_command", metavar="ACTION")
    yolo.set_defaults(func=lambda _args: yolo.print_help() or 2)

    p = actions.add_parser(
        "eval", help="per-frame detections, mask area and removed keypoints on a sequence",
        description="Runs the masker on every --step-th frame, detects keypoints on the same frames, and writes "
        "frames.csv (per frame), summary.json and eval.png to --out. Both the box mask and the depth-refined "
        "mask are measured from the same detections.",
    )
    p.add_argument("--sequence", default=DEV_SEQUENCE, help=f"TUM-layout RGB-D folder (default {DEV_SEQUENCE})")
    p.add_argument("--step", type=int, default=5, help="evaluate every N-th frame (default 5)")
    p.add_argument("--start", type=int, default=0, help="first frame (default 0)")
    p.add_argument("--frames", type=int, default=None, help="evaluate at most this many frames (default: to the end)")
    p.add_argument("--every-n", type=int, help="run the detector on every N-th evaluated frame, propagate between")
    p.add_argument("--keypoints", choices=KEYPOINT_CHOICES, default="2hr",
                   help="keypoints to filter (default 2hr, the detector core's default); none = skip")
    p.add_argument("--out", default="runs/yolo", help="output folder (default runs/yolo)")
    _common(p)
    _mask_options(p)
    p.set_defaults(func=_eval)

    p = actions.add_parser(
        "viz", help="draw boxes, masks and kept/removed keypoints for a few frames",
        description="One PNG per frame: the box mask (left) and the depth-refined mask (right), every detection "
        "boxed in its level's colour (red high, orange medium, yellow low, grey static), kept keypoints green "
        "and removed ones magenta.",
    )
    p.add_argument("--sequence", default=DEV_SEQUENCE, help=f"TUM-layout RGB-D folder (default {DEV_SEQUENCE})")
    p.add_argument("--indices", type=_frame_list, default=[100, 320, 445], metavar="I,J,...",
                   help="comma-separated frame numbers to draw (default 100,320,445)")
    p.add_argument("--keypoints", choices=KEYPOINT_CHOICES, default="2hr", help="keypoints to draw (default 2hr)")
    p.add_argument("--out", default="runs/yolo/viz", help="output folder (default runs/yolo/viz)")
    p.add_argument("--scale", type=float, default=1.0, help="resize the pictures by this factor (default 1)")
    _common(p)
    _mask_options(p)
    p.set_defaults(func=_viz)

    p = actions.add_parser(
        "bench", help="milliseconds per frame of the YOLO models (median of N runs)",
        description="Times YoloDetector.detect (letterbox, network, decode, NMS) for each model on 640x480 frames, "
        "with the bare onnxruntime call as the in-run baseline, plus the box and depth masks.",
    )
    p.add_argument("--sequence", default=DEV_SEQUENCE,
                   help="frames to time on (default the dev sequence; a synthetic frame if it is absent)")
    p.add_argument("--models", type=lambda s: [x.strip() for x in s.split(",") if x.strip()],
                   default=["yolov8n_320", "yolov8n", "yolov5n_320", "yolov5n"],
                   help="comma-separated models; the first is the ratio baseline")
    p.add_argument("--runs", type=int, default=10, help="rounds over the frames (default 10)")
    p.add_argument("--threads", type=int, default=2, help="onnxruntime threads (default 2)")
    p.add_argument("--json", help="also write the result as JSON here")
    p.set_defaults(func=_bench)

    p = actions.add_parser(
        "propagation", help="how well every-n-th-frame detection with propagated masks covers the objects",
        description="Detects on every frame, then for each --every-n and --growth compares the box mask "
        "propagated from the latest detection with the box mask of each in-between frame's own detections.",
    )
    p.add_argument("--sequence", default=DEV_SEQUENCE, help=f"TUM-layout RGB-D folder (default {DEV_SEQUENCE})")
    p.add_argument("--every-n", dest="intervals", type=lambda s: [int(x) for x in s.split(",")], default=[2, 3, 5],
                   help="detection intervals to compare (default 2,3,5)")
    p.add_argument("--growth", type=lambda s: [float(x) for x in s.split(",")], default=[0.0, 0.04, 0.08, 0.12],
                   help="box growth per elapsed frame, fraction of box width (default 0,0.04,0.08,0.12)")
    p.add_argument("--start", type=int, default=0, help="first frame (default 0)")
    p.add_argument("--frames", type=int, default=None, help="use this many frames from --start (default: to the end)")
    p.add_argument("--json", help="also write the table as JSON here")
    _common(p)
    p.set_defaults(func=_propagation)

    p = actions.add_parser("detect", help="print the detections of one image with their dynamics level")
    p.add_argument("image", help="an image file (JPEG, PNG, ...)")
    _common(p)
    p.add_argument("--table", help="dynamics table YAML (default: the paper's table)")
    p.set_defaults(func=_detect)
