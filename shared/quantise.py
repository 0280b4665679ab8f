"""INT8 keyframe networks with their heads kept in float (issue 41).

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

