"""Keyframe networks built from registered ones (issue 41): INT8 with the heads in float, and heads before the
upsample (:func:`heads_before_upsample`).

An R2D2-contract network (``image`` -> ``descriptors``, ``reliability``, ``repeatability``) is quantised by
onnxruntime's static QDQ quantisation: int8 per-channel weights, uint8 activations, MinMax ranges. Only the
convolutional trunk is quantised. The heads stay in float (:func:`head_nodes`): quantised, the repeatability
head ``softplus(s) / (1 + softplus(s))`` calibrates its softplus to a range of about 1000, so both numerator and
denominator round to 0 on most pixels and 0/0 gives NaN (``lab/student/int8.py`` traces it).

The activation ranges are measured once on training images (never the evaluation frames) and shipped as a small
JSON file (onnxruntime's calibration cache), so the INT8 file is rebuilt from the float model anywhere, byte for
byte, without the images: ``twohr models fetch faster2d2_WASF_N16_int8``.
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

OUTPUTS = ("descriptors", "reliability", "repeatability")
#: the ops of the trunk that are quantised; everything else stays float
QUANTISED_OPS = ["Conv", "MaxPool", "Relu"]


def head_nodes(model) -> list[str]:
    """Names of the head nodes of an ONNX ``model``: every node on a path to an output that the descriptor
    features (the tensor the final L2 normalisation divides) do not need. For faster2d2 and r2d2 these are the
    x*x, the reliability conv/softmax, the repeatability conv/softplus/add/div and the L2 normalisation."""
    producers = {out: node for node in model.graph.node for out in node.output}

    def ancestors(tensors: Iterable[str]) -> set[str]:
        seen: set[str] = set()
        stack = list(tensors)
        while stack:
            node = producers.get(stack.pop())
            if node is None or node.name in seen:
                continue
            seen.add(node.name)
            stack.extend(node.input)
        return seen

    trunk = ancestors([producers["descriptors"].input[0]])
    return [node.name for node in model.graph.node if node.name in ancestors(OUTPUTS) - trunk]


class ImageBatches:
    """onnxruntime ``CalibrationDataReader`` over RGB images (a callable turning one path into the network's
    ``[1, 3, H, W]`` float input)."""

    def __init__(self, paths: list[Path], to_input) -> None:
        self.paths, self.to_input = list(paths), to_input
        self._iter: Iterator[Path] = iter(self.paths)

    def get_next(self):
        path = next(self._iter, None)
        return None if path is None else {"image": self.to_input(path)}

    def rewind(self) -> None:
        self._iter = iter(self.paths)


def quantise_heads_float(source: Path, target: Path, ranges: Path, calibration: ImageBatches | None = None,
                         keep_heads_float: bool = True, extra_ops: Iterable[str] = ()) -> Path:
    """Write the INT8 (QDQ) version of ``source`` to ``target``.

    ``ranges`` is the calibration cache: read when it exists (then ``calibration`` is not needed), else measured
    on ``calibration`` and written there. ``keep_heads_float=False`` quantises the heads as well (with
    ``extra_ops``), which only the study of the NaN does.
    """
    import onnx
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    if not Path(ranges).is_file() and calibration is None:
        raise FileNotFoundError(f"no activation ranges at {ranges} and no calibration images to measure them")
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        pre = Path(tmp) / "pre.onnx"
        quant_pre_process(str(source), str(pre), skip_symbolic_shape=False)
        exclude = head_nodes(onnx.load(str(pre))) if keep_heads_float else []
        quantize_static(
            str(pre), str(target), calibration,
            quant_format=QuantFormat.QDQ, per_channel=True, activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8, calibrate_method=CalibrationMethod.MinMax,
            op_types_to_quantize=[*QUANTISED_OPS, *extra_ops], nodes_to_exclude=exclude,
            extra_options={"ActivationSymmetric": False, "WeightSymmetric": True},
            calibration_cache_path=str(ranges),
        )
    return target


def heads_before_upsample(source: Path, target: Path) -> None:
    """Write ``source`` (a faster2d2-shaped graph, float or INT8) with its heads moved before the final 2x upsample.

    faster2d2 upsamples its 128-channel features 2x, squares them and runs the reliability and repeatability 1x1
    convolutions at full resolution: about half of the INT8 network's time. Here the square and the head
    convolutions run on the features before the upsample, and only their 1- and 2-channel logits are upsampled
    (the same bilinear Resize), so the 128-channel upsample goes: the detector already reads descriptors from the
    features before it. The logits are an approximation (upsampling does not commute with the square), so the
    keypoints move a little; the descriptors do not.
    """
    import onnx
    from onnx import helper

    model = onnx.load(str(source))
    graph = model.graph
    producers = {out: node for node in graph.node for out in node.output}
    square = next((n for n in graph.node if n.op_type == "Mul" and n.input[0] == n.input[1]
                   and getattr(producers.get(n.input[0]), "op_type", "") == "Resize"), None)
    if square is None:
        raise ValueError(f"{source}: no square of an upsampled tensor: not a faster2d2-shaped graph")
    resize = producers[square.input[0]]
    heads = [n for n in graph.node if n.op_type == "Conv" and n.input[0] == square.output[0]]
    features = resize.input[0]
    moved = [helper.make_node("Mul", [features, features], [f"{square.output[0]}_coarse"],
                              name=f"{square.name}_coarse")]
    for head in heads:
        conv = helper.make_node("Conv", [moved[0].output[0], *head.input[1:]], [f"{head.output[0]}_coarse"],
                                name=f"{head.name}_coarse")
        conv.attribute.extend(head.attribute)
        upsample = helper.make_node("Resize", [conv.output[0], *resize.input[1:]], [head.output[0]],
                                    name=f"{head.name}_upsample")
        upsample.attribute.extend(resize.attribute)
        moved += [conv, upsample]
    nodes = []
    for node in graph.node:
        if node is square:
            nodes += moved
        elif not any(node is head for head in heads):
            nodes.append(node)
    del graph.node[:]
    graph.node.extend(nodes)
    onnx.checker.check_model(model)
    onnx.save(model, str(target))
