"""INT8 study (issue 41, part 1): why INT8 R2D2 gave NaN repeatability, and an INT8 faster2d2 that does not.

What it does (``python -m twohr_lab.student.int8 --out runs/student``):

1. **inspect** a quantised graph: for every compute node, whether its inputs come through a
   DequantizeLinear (quantised) or stay float (:func:`node_table`);
2. **reproduce** the failure: quantise faster2d2 *with* its heads (the x*x feeding the heads, the
   reliability softmax, the repeatability softplus / (1 + softplus), the L2 normalisation) and trace the
   first tensor that turns NaN (:func:`first_nan`), with the quantisation parameters that make it so;
3. **fix**: onnxruntime static quantisation, QDQ, per-channel int8 weights, uint8 activations, MinMax
   calibration on ~200 training images at 480x360, with every head node excluded (kept in float)
   (:func:`quantise`), written to ``<out>/faster2d2_WASF_N16_int8_heads_f32.onnx``;
4. **measure** latency against faster2d2 f32 (onnxruntime, 1 thread, 480x360, median of 5 runs of 20
   inferences) and closeness (descriptor cosine, absolute differences of the maps, keypoints within 1 px)
   on held-out images (:func:`compare`, :func:`latency`).

Heavy: run it under ``nice -n 19`` with ``OMP_NUM_THREADS=1``; it sets 1 onnxruntime thread itself.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

from twohr.quantise import ImageBatches, quantise_heads_float

from .data import images_dir, list_images, models_dir, network_input, split, spread

MODELS = models_dir()
TEACHER = MODELS / "faster2d2_WASF_N16.onnx"
R2D2_INT8 = MODELS / "r2d2_WASF_N16_int8.onnx"
R2D2_F32 = MODELS / "r2d2_WASF_N16.onnx"
OUTPUTS = ("descriptors", "reliability", "repeatability")
SIZE = (480, 360)  # (width, height)
#: ops of the heads, quantised as well in the "naive" reproduction (what a quantise-everything tool does)
HEAD_OPS = ["Mul", "Add", "Div", "Softmax", "Softplus", "ReduceL2", "Clip", "Expand", "Slice", "Resize"]


def session(model: str | bytes | Path, threads: int = 1):
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return ort.InferenceSession(str(model) if isinstance(model, Path) else model, options,
                                providers=["CPUExecutionProvider"])


# ----------------------------------------------------------------------------- graph inspection


def node_table(path: str | Path) -> list[dict]:
    """For each compute node of a (QDQ) graph: op, name, and which data inputs are quantised (come
    through DequantizeLinear) and whether its output is re-quantised (feeds a QuantizeLinear)."""
    import onnx

    model = onnx.load(str(path))
    producers = {out: node for node in model.graph.node for out in node.output}
    consumers: dict[str, list] = {}
    for node in model.graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)
    rows = []
    for node in model.graph.node:
        if node.op_type in ("QuantizeLinear", "DequantizeLinear", "Constant"):
            continue
        inputs = []
        for name in node.input:
            if not name:
                continue
            src = producers.get(name)
            inputs.append("q" if src is not None and src.op_type == "DequantizeLinear" else "f")
        requant = any(c.op_type == "QuantizeLinear" for out in node.output for c in consumers.get(out, []))
        rows.append({"op": node.op_type, "name": node.name, "inputs": "".join(inputs), "output_requantised": requant})
    return rows


def quant_params(path: str | Path) -> dict[str, tuple[float, int]]:
    """(scale, zero_point) of every per-tensor activation QuantizeLinear, by the tensor it quantises."""
    import onnx
    from onnx import numpy_helper

    model = onnx.load(str(path))
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    params = {}
    for node in model.graph.node:
        if node.op_type == "QuantizeLinear" and node.input[1] in inits and inits[node.input[1]].size == 1:
            params[node.input[0]] = (float(inits[node.input[1]]), int(inits[node.input[2]]))
    return params


def with_all_outputs(path: str | Path) -> bytes:
    """The model with every node output also a graph output (to find where NaN first appears)."""
    import onnx

    model = onnx.load(str(path))
    existing = {o.name for o in model.graph.output}
    for node in model.graph.node:
        for name in node.output:
            if name and name not in existing:
                model.graph.output.append(onnx.ValueInfoProto(name=name))
                existing.add(name)
    return model.SerializeToString()


def first_nan(path: str | Path, image: np.ndarray) -> dict | None:
    """The first node (in graph order) whose output holds NaN for ``image``, with its inputs' statistics."""
    import onnx

    model = onnx.load(str(path))
    sess = session(with_all_outputs(path))
    names = [o.name for o in sess.get_outputs()]
    values = dict(zip(names, sess.run(names, {"image": image}), strict=True))
    for node in model.graph.node:
        for out in node.output:
            value = values.get(out)
            if value is not None and value.dtype.kind == "f" and np.isnan(value).any():
                stats = {}
                for name in node.input:
                    if name in values and values[name].dtype.kind in "fiu":
                        v = values[name].astype(np.float64)
                        stats[name] = {"min": float(v.min()), "max": float(v.max()),
                                       "zero_fraction": float((v == 0).mean()), "size": int(v.size)}
                return {"node": node.name, "op": node.op_type, "output": out,
                        "nan_fraction": float(np.isnan(value).mean()), "inputs": stats}
    return None


def without_output_qdq(path: str | Path) -> bytes:
    """The QDQ model with the Quantize/DequantizeLinear pairs in front of the graph outputs removed, as a
    tool that quantises op inputs only (NNCF's default) leaves them: the outputs are then the float results
    of the (quantised-input) head ops. onnxruntime's output QuantizeLinear turns a NaN into 0 and so hides it."""
    import onnx

    model = onnx.load(str(path))
    graph = model.graph
    producers = {out: node for node in graph.node for out in node.output}
    drop = []
    for output in graph.output:
        dq = producers.get(output.name)
        if dq is None or dq.op_type != "DequantizeLinear":
            continue
        q = producers.get(dq.input[0])
        if q is None or q.op_type != "QuantizeLinear":
            continue
        float_tensor = q.input[0]
        producers[float_tensor].output[list(producers[float_tensor].output).index(float_tensor)] = output.name
        drop += [q, dq]
    for node in drop:
        graph.node.remove(node)
    return model.SerializeToString()


# ----------------------------------------------------------------------------- quantisation


def quantise(src: Path, dst: Path, calibration: list[Path], keep_heads_float: bool = True,
             size: tuple[int, int] = SIZE) -> Path:
    """:func:`twohr.quantise.quantise_heads_float` calibrated on ``calibration`` images at ``size``; the activation
    ranges are written beside ``dst`` (``<dst stem>.ranges.json``, what the registry ships).

    Without ``keep_heads_float`` the head ops are quantised as well (:data:`HEAD_OPS`), which reproduces the NaN.
    """
    ranges = dst.with_name(dst.stem + ".ranges.json")
    ranges.unlink(missing_ok=True)
    reader = ImageBatches(calibration, lambda path: network_input(path, *size))
    return quantise_heads_float(src, dst, ranges, reader, keep_heads_float, () if keep_heads_float else HEAD_OPS)


# ----------------------------------------------------------------------------- measurements


def _peaks(rel: np.ndarray, rep: np.ndarray, floor: float = 0.7) -> np.ndarray:
    """(N, 2) R2D2 keypoints: 3x3 maxima of repeatability with both maps >= floor."""
    import cv2

    dilated = cv2.dilate(rep, np.ones((3, 3), np.uint8))
    ys, xs = np.nonzero((rep == dilated) & (rep >= floor) & (rel >= floor))
    return np.stack([xs, ys], 1).astype(np.float32)


def compare(reference: str | Path | bytes, candidate: str | Path | bytes, images: list[Path],
            size: tuple[int, int] = SIZE) -> dict:
    """Closeness of ``candidate`` to ``reference`` on ``images``: NaN/inf counts, per-pixel descriptor
    cosine, absolute differences of the reliability and repeatability maps, and the fraction of the
    reference's keypoints that the candidate has within 1 px."""
    import cv2

    ref, cand = session(reference), session(candidate)
    cos, rel_diff, rep_diff, rel_max, rep_max, within, nonfinite, kp_ref, kp_cand = ([] for _ in range(9))
    for path in images:
        x = network_input(path, *size)
        a = dict(zip(OUTPUTS, ref.run(list(OUTPUTS), {"image": x}), strict=True))
        b = dict(zip(OUTPUTS, cand.run(list(OUTPUTS), {"image": x}), strict=True))
        nonfinite.append({k: int((~np.isfinite(b[k])).sum()) for k in OUTPUTS})
        c = (a["descriptors"] * b["descriptors"]).sum(1)
        cos.append(float(np.nanmean(c)))
        dr = np.abs(a["reliability"] - b["reliability"])
        dp = np.abs(a["repeatability"] - b["repeatability"])
        rel_diff.append(float(np.nanmean(dr)))
        rep_diff.append(float(np.nanmean(dp)))
        rel_max.append(float(np.nanmax(dr)) if np.isfinite(dr).any() else float("nan"))
        rep_max.append(float(np.nanmax(dp)) if np.isfinite(dp).any() else float("nan"))
        pa = _peaks(a["reliability"][0, 0], a["repeatability"][0, 0])
        pb = _peaks(np.nan_to_num(b["reliability"][0, 0]), np.nan_to_num(b["repeatability"][0, 0]))
        kp_ref.append(len(pa))
        kp_cand.append(len(pb))
        if len(pa) and len(pb):
            grid = np.zeros(b["repeatability"].shape[2:], np.uint8)
            grid[pb[:, 1].astype(int), pb[:, 0].astype(int)] = 1
            grid = cv2.dilate(grid, np.ones((3, 3), np.uint8))
            within.append(float(grid[pa[:, 1].astype(int), pa[:, 0].astype(int)].mean()))
        else:
            within.append(0.0)
    return {
        "images": len(images),
        "nonfinite_pixels": {k: sum(n[k] for n in nonfinite) for k in OUTPUTS},
        "descriptor_cosine_mean": float(np.mean(cos)), "descriptor_cosine_min_image": float(np.min(cos)),
        "reliability_absdiff_mean": float(np.mean(rel_diff)), "reliability_absdiff_max": float(np.max(rel_max)),
        "repeatability_absdiff_mean": float(np.mean(rep_diff)),
        "repeatability_absdiff_max": float(np.max(rep_max)),
        "keypoints_reference_mean": float(np.mean(kp_ref)), "keypoints_candidate_mean": float(np.mean(kp_cand)),
        "reference_keypoints_within_1px": float(np.mean(within)),
    }


def latency(model: str | Path | bytes, size: tuple[int, int] = SIZE, runs: int = 5, per_run: int = 20) -> dict:
    """ms per inference, onnxruntime with 1 thread: median (and min, max) over ``runs`` runs of ``per_run``."""
    sess = session(model)
    x = np.random.default_rng(0).standard_normal((1, 3, size[1], size[0])).astype(np.float32)
    for _ in range(3):
        sess.run(None, {"image": x})
    per = []
    for _ in range(runs):
        start = time.perf_counter()
        for _ in range(per_run):
            sess.run(None, {"image": x})
        per.append((time.perf_counter() - start) * 1000 / per_run)
    return {"median_ms": statistics.median(per), "min_ms": min(per), "max_ms": max(per), "runs_ms": per}


def cpu_model() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return "unknown"


# ----------------------------------------------------------------------------- the study


def study(images_dir: Path, out: Path, calibration_count: int = 200, check_count: int = 20) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    train, held = split(list_images(images_dir))
    calibration = spread(train, calibration_count)
    check = spread(held or train, check_count)
    report: dict = {"cpu": cpu_model(), "size": SIZE, "calibration_images": len(calibration),
                    "check_images": len(check)}

    # 1. the shared r2d2 INT8 file: which nodes are quantised, and does it give NaN?
    report["r2d2_int8_nodes"] = node_table(R2D2_INT8)
    report["r2d2_int8_vs_f32"] = compare(R2D2_F32, R2D2_INT8, check[:5])

    # 2. reproduce: faster2d2 quantised with its heads
    naive = quantise(TEACHER, out / "faster2d2_int8_naive_all_ops.onnx", calibration, keep_heads_float=False)
    report["naive_nodes"] = node_table(naive)
    report["naive_vs_f32"] = compare(TEACHER, naive, check)
    report["naive_first_nan"] = [first_nan(naive, network_input(p, *SIZE)) for p in check[:3]]
    report["naive_without_output_qdq_vs_f32"] = compare(TEACHER, without_output_qdq(naive), check[:3])
    params = quant_params(naive)
    report["naive_head_qparams"] = {k: v for k, v in params.items() if not k.startswith("/ops.")}

    # 3. fix: heads in float
    fixed = quantise(TEACHER, out / "faster2d2_WASF_N16_int8_heads_f32.onnx", calibration, keep_heads_float=True)
    report["fixed_nodes"] = node_table(fixed)
    report["fixed_vs_f32"] = compare(TEACHER, fixed, check)

    # 4. latency
    report["latency_faster2d2_f32"] = latency(TEACHER)
    report["latency_faster2d2_int8"] = latency(fixed)
    (out / "int8_report.json").write_text(json.dumps(report, indent=1))
    return report


def markdown(r: dict, latency_extra: dict | None = None) -> str:
    """The study as a short Markdown report."""
    def row(name: str, c: dict) -> str:
        nonfinite = sum(c["nonfinite_pixels"].values())
        return (f"| {name} | {c['images']} | {nonfinite} | {c['descriptor_cosine_mean']:.4f} | "
                f"{c['reliability_absdiff_mean']:.4f} / {c['reliability_absdiff_max']:.2f} | "
                f"{c['repeatability_absdiff_mean']:.4f} / {c['repeatability_absdiff_max']:.2f} | "
                f"{c['keypoints_reference_mean']:.0f} / {c['keypoints_candidate_mean']:.0f} | "
                f"{100 * c['reference_keypoints_within_1px']:.1f} % |")

    nan = r["naive_first_nan"][0]
    sp = r["naive_head_qparams"]["/Softplus_output_0"]
    add = r["naive_head_qparams"]["/Add_output_0"]
    lines = [
        "# INT8 keyframe network: the NaN repeatability, and faster2d2 INT8 with float heads", "",
        f"CPU: {r['cpu']}; input {r['size'][0]}x{r['size'][1]}; calibration: {r['calibration_images']} training "
        f"images (MinMax); checks: {r['check_images']} held-out images (last 200 frames of 7scenes).", "",
        "## Root cause", "",
        "R2D2's repeatability head is `s = softplus(conv(x*x)); repeatability = s / (1 + s)`, fed by the *square* of "
        "the descriptor features, so its calibrated range is set by rare huge values: softplus reaches "
        f"~{nan['inputs'][next(iter(nan['inputs']))]['max']:.0f} on one image. Quantised per tensor to uint8, "
        f"softplus gets scale {sp[0]:.2f} (zero point {sp[1]}) and `1 + s` scale {add[0]:.2f}: every pixel with "
        f"`1 + s < {add[0] / 2:.2f}` (most of the image) rounds to 0 in *both* numerator and denominator, and the "
        f"Div gives 0/0 = NaN (first NaN tensor: `{nan['node']}` ({nan['op']}), "
        f"{100 * nan['nan_fraction']:.1f} % of pixels; both inputs exactly 0 there). "
        "onnxruntime's QuantizeLinear on the graph output turns those NaN into 0 (a binary map: 0 or 0.999, "
        "~18 k 'keypoints' per image); with the output Quantize/DequantizeLinear removed (as a tool that quantises "
        "op inputs only leaves the outputs) the NaN reaches the output (row 'NNCF-like' below). The earlier NNCF "
        "try on faster2d2 (noted in results/accuracy/README.md) is consistent with this but was not rerun here "
        "(NNCF is not installed). The same trap sits in the L2 normalisation: a quantised "
        "`Clip(ReduceL2(x), 1e-12)` loses its epsilon (scale "
        f"{r['naive_head_qparams']['/Clip_output_0'][0]:.3f}), so a weak descriptor gives x/0.",
        "",
        "The shared `r2d2_WASF_N16_int8.onnx` keeps these heads in float (its Mul/ReduceL2 read dequantised "
        "features; sal/clf convs, softplus, softmax and both Divs are float) and gives no NaN here, on onnxruntime "
        "and on OpenVINO f32/bf16, on real and on blank/noise images.", "",
        "## Closeness to faster2d2 f32", "",
        "| model | images | non-finite px | desc cosine | rel abs diff mean / max | rep abs diff mean / max | "
        "keypoints f32 / model | f32 keypoints within 1 px |",
        "|---|---|---|---|---|---|---|---|",
        row("r2d2 INT8 (shared file) vs r2d2 f32", r["r2d2_int8_vs_f32"]),
        row("faster2d2 INT8, heads quantised (naive)", r["naive_vs_f32"]),
    ]
    if "naive_without_output_qdq_vs_f32" in r:
        lines.append(row("naive, outputs not re-quantised (NNCF-like)", r["naive_without_output_qdq_vs_f32"]))
    lines += [
        row("**faster2d2 INT8, heads float (fix)**", r["fixed_vs_f32"]), "",
        "## Latency (onnxruntime, 1 thread, median of 5 runs of 20 inferences, dense graphs)", "",
        f"- faster2d2 f32: {r['latency_faster2d2_f32']['median_ms']:.1f} ms",
        f"- faster2d2 INT8, heads float: {r['latency_faster2d2_int8']['median_ms']:.1f} ms "
        f"({r['latency_faster2d2_f32']['median_ms'] / r['latency_faster2d2_int8']['median_ms']:.2f}x)",
        "", "The machine is shared (another engineer's benchmarks ran at the same time): compare only figures "
        "from one run.", "",
    ]
    if latency_extra:
        lines += ["## Detector graph (sparse descriptors) and the student", "",
                  "| network | dense ONNX ms | detector graph ms |", "|---|---|---|"]
        for name, v in latency_extra.items():
            if isinstance(v, dict) and "dense" in v:
                lines.append(f"| {name} | {v['dense']['median_ms']:.1f} | {v['detector_sparse']['median_ms']:.1f} |")
        lines.append("")
    return "\n".join(lines)


def quantise_other(model: Path, out: Path, images_dir: Path, calibration_count: int = 200,
                   check_count: int = 10) -> dict:
    """The fix applied to another R2D2-contract ONNX (e.g. the student): heads float, the rest INT8; compared
    with its own f32 export and with faster2d2, and timed (onnxruntime, 1 thread, :func:`latency`)."""
    train, held = split(list_images(images_dir))
    dst = quantise(model, out / f"{model.stem}_int8_heads_f32.onnx", spread(train, calibration_count))
    check = spread(held or train, check_count)
    report = {"model": str(model), "int8": str(dst), "int8_vs_f32": compare(model, dst, check),
              "int8_vs_faster2d2": compare(TEACHER, dst, check), "f32_vs_faster2d2": compare(TEACHER, model, check),
              "latency": {name: latency(path) for name, path in
                          {"faster2d2_f32": TEACHER, "model_f32": model, "model_int8_heads_f32": dst}.items()}}
    (out / f"{model.stem}_int8_report.json").write_text(json.dumps(report, indent=1))
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m twohr_lab.student.int8", description=__doc__.split("\n")[0])
    parser.add_argument("--images", default=str(images_dir()), help="calibration images (never the eval data)")
    parser.add_argument("--out", default="runs/student", help="output folder")
    parser.add_argument("--calibration", type=int, default=200, help="number of calibration images")
    parser.add_argument("--check", type=int, default=20, help="held-out images for the comparison")
    parser.add_argument("--report-only", action="store_true", help="rewrite int8_report.md from int8_report.json")
    parser.add_argument("--model", help="instead of the study: quantise this R2D2-contract ONNX (heads float)")
    args = parser.parse_args(argv)
    out = Path(args.out)
    if args.model:
        report = quantise_other(Path(args.model), out, Path(args.images), args.calibration, args.check)
        print(json.dumps({k: v for k, v in report.items()}, indent=1))
        return 0
    if args.report_only:
        report = json.loads((out / "int8_report.json").read_text())
        extra = out / "latency.json"
        (out / "int8_report.md").write_text(markdown(report, json.loads(extra.read_text()) if extra.exists() else None))
        print(out / "int8_report.md")
        return 0
    report = study(Path(args.images), Path(args.out), args.calibration, args.check)
    (out / "int8_report.md").write_text(markdown(report))
    brief = {k: v for k, v in report.items() if not k.endswith("_nodes")}
    print(json.dumps(brief, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
