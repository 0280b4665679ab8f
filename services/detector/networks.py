"""The R2D2-family networks: one ONNX Runtime session (or OpenVINO model) per process, model, thread count and
precision, with input and output buffers reused per size. The graph is run with its dense descriptor normalisation
cut off where it can be, and :class:`R2D2Maps` finishes the descriptors at the few kept keypoints."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from functools import cache

import cv2
import numpy as np
import onnxruntime as ort

from twohr.models import ORT_PROVIDERS, Network, keyframe_network, model_path, ort_session, resolve_backend

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)
DESCRIPTOR_DIM = 128


@dataclass
class R2D2Maps:
    """Network outputs for one image.

    ``reliability`` and ``repeatability`` are (h, w) at network resolution. ``features`` is the raw
    (not yet normalised) 128-channel descriptor map at ``1 / feature_stride`` of that resolution;
    :meth:`descriptors_at` turns it into unit descriptors at given pixels. The arrays are views into
    reused buffers: copy them to keep them past the next call of the same network.
    """

    features: np.ndarray
    reliability: np.ndarray
    repeatability: np.ndarray
    feature_stride: int = 1

    def descriptors_at(self, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
        """L2-normalised descriptors (N, 128) float32 at network pixels (ys, xs).

        With stride 2 the feature map is the one the network upsamples bilinearly (half-pixel
        centres), so sampling it bilinearly here gives the same values the dense output would have.
        """
        ys = np.asarray(ys)
        xs = np.asarray(xs)
        if self.feature_stride == 1:
            raw = self.features[:, ys, xs].T
        else:
            raw = _bilinear_at(self.features, (ys + 0.5) / self.feature_stride - 0.5,
                               (xs + 0.5) / self.feature_stride - 0.5)
        raw = np.ascontiguousarray(raw, dtype=np.float32)
        norms = np.linalg.norm(raw, axis=1, keepdims=True)
        return raw / np.maximum(norms, 1e-12)


def _bilinear_at(maps: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """Samples (N, C) of a (C, h, w) map at float coordinates, clamped to the border (ONNX Resize semantics)."""
    channels, height, width = maps.shape
    ys = np.clip(ys, 0, height - 1)
    xs = np.clip(xs, 0, width - 1)
    y0 = np.floor(ys).astype(np.int64)
    x0 = np.floor(xs).astype(np.int64)
    y1 = np.minimum(y0 + 1, height - 1)
    x1 = np.minimum(x0 + 1, width - 1)
    fy = (ys - y0).astype(np.float32)
    fx = (xs - x0).astype(np.float32)
    # one gather of the four corners, then their weighted sum
    corners = np.concatenate([y0 * width + x0, y0 * width + x1, y1 * width + x0, y1 * width + x1])
    values = np.take(maps.reshape(channels, -1), corners, axis=1).reshape(channels, 4, -1)
    weights = np.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx])
    return np.einsum("ckn,kn->nc", values, weights)


@dataclass(frozen=True)
class _PreparedModel:
    model: bytes
    feature_stride: int


@cache
def _prepare_model(path: str, sparse_descriptors: bool) -> _PreparedModel:
    """The ONNX graph to run, with the dense descriptor normalisation cut off when possible.

    The exported graph ends in ``descriptors = x / max(||x||, eps)`` over the whole 128xHxW map,
    and faster2d2 computes ``x`` by a 2x bilinear upsample. Both only matter at the few
    keypoints, so the graph is made to output the tensor before them (``x``, or the tensor before
    the upsample) and :meth:`R2D2Maps.descriptors_at` finishes the job per keypoint. Graphs of
    another shape are run unchanged.
    """
    import onnx
    from onnx import helper, numpy_helper

    model = onnx.load(path)
    if not sparse_descriptors:
        return _PreparedModel(model.SerializeToString(), 1)
    graph = model.graph
    producers = {out: node for node in graph.node for out in node.output}
    constants = {init.name: numpy_helper.to_array(init) for init in graph.initializer}
    for node in graph.node:
        if node.op_type == "Constant":
            constants[node.output[0]] = numpy_helper.to_array(node.attribute[0].t)
    div = producers.get("descriptors")
    if div is None or not _is_l2_normalisation(div, producers):
        return _PreparedModel(model.SerializeToString(), 1)
    feature, stride = div.input[0], 1
    resize = producers.get(feature)
    if resize is not None and resize.op_type == "Resize" and _is_2x_bilinear(resize, constants):
        feature, stride = resize.input[0], 2
    nodes = [node for node in graph.node if node is not div]
    nodes.append(helper.make_node("Identity", [feature], ["descriptors"], name="raw_descriptor_features"))
    # drop the nodes that only fed the normalisation
    needed = {output.name for output in graph.output}
    alive = []
    for node in reversed(nodes):
        if any(out in needed for out in node.output):
            alive.append(node)
            needed.update(name for name in node.input if name)
    del graph.node[:]
    graph.node.extend(reversed(alive))
    for output in graph.output:
        if output.name == "descriptors":
            output.type.tensor_type.ClearField("shape")
    unused = [init for init in graph.initializer if init.name not in needed]
    for init in unused:
        graph.initializer.remove(init)
    return _PreparedModel(model.SerializeToString(), stride)


def _is_l2_normalisation(div, producers: dict) -> bool:
    """True for ``Div(x, f(ReduceL2(x)))`` where f is a short chain of shape/clip ops (the R2D2 export)."""
    if div.op_type != "Div":
        return False
    node = producers.get(div.input[1])
    for _ in range(4):
        if node is None:
            return False
        if node.op_type == "ReduceL2":
            return node.input[0] == div.input[0]
        if node.op_type not in ("Expand", "Clip", "Max", "Unsqueeze"):
            return False
        node = producers.get(node.input[0])
    return False


def _is_2x_bilinear(node, constants: dict[str, np.ndarray]) -> bool:
    attrs = {a.name: (a.s.decode() if a.s else a.i) for a in node.attribute}
    scales = constants.get(node.input[2]) if len(node.input) > 2 else None
    return (attrs.get("mode") == "linear" and attrs.get("coordinate_transformation_mode", "half_pixel") == "half_pixel"
            and scales is not None and np.allclose(scales, [1, 1, 2, 2]))


@cache
def _session(path: str, threads: int, sparse_descriptors: bool, backend: str = "onnxruntime",
             precision: str = "auto") -> tuple[ort.InferenceSession, _PreparedModel]:
    prepared = _prepare_model(path, sparse_descriptors)
    session = ort_session(prepared.model, threads, backend, precision)
    return session, prepared


class R2D2Network:
    """One onnxruntime session per process, model and thread count; input and output buffers reused per size.

    ``sparse_descriptors=False`` runs the exported graph unchanged (dense, normalised descriptors):
    slower, kept as the reference for tests and benchmarks.
    """

    def __init__(self, model: str = "faster2d2_WASF_N16", threads: int = 2, sparse_descriptors: bool = True,
                 backend: str = "onnxruntime", precision: str = "auto") -> None:
        self.model = keyframe_network(model)
        self.threads = threads
        self.backend = resolve_backend(backend)
        path = str(model_path(self.model, kind="r2d2"))
        if self.backend not in ORT_PROVIDERS:  # OpenVINO, on the CPU or a GPU
            prepared = _prepare_model(path, sparse_descriptors)
            self.openvino = Network(prepared.model, threads, self.backend, precision)  # compiled per input size
        else:
            self.session, prepared = _session(path, threads, sparse_descriptors, self.backend, precision)
        self.feature_stride = prepared.feature_stride
        self._buffers: dict[tuple[int, int], tuple[np.ndarray, dict[str, np.ndarray], ort.IOBinding]] = {}
        self._lock = threading.Lock()

    def _binding(self, width: int, height: int):
        key = (width, height)
        if key not in self._buffers:
            stride = self.feature_stride
            if width % stride or height % stride:
                raise ValueError(f"{self.model} needs an input size divisible by {stride}, got {width}x{height}")
            image = np.zeros((1, 3, height, width), np.float32)
            outputs = {
                "descriptors": np.zeros((1, DESCRIPTOR_DIM, height // stride, width // stride), np.float32),
                "reliability": np.zeros((1, 1, height, width), np.float32),
                "repeatability": np.zeros((1, 1, height, width), np.float32),
            }
            if self.backend not in ORT_PROVIDERS:
                self._buffers[key] = (image, outputs, None)
                return self._buffers[key]
            binding = self.session.io_binding()
            binding.bind_cpu_input("image", image)
            for name, array in outputs.items():
                binding.bind_output(name, "cpu", 0, np.float32, array.shape, array.ctypes.data)
            self._buffers[key] = (image, outputs, binding)
        return self._buffers[key]

    def __call__(self, rgb: np.ndarray, size: tuple[int, int]) -> R2D2Maps:
        """Run the network on an RGB uint8 image resized to ``size`` = (width, height)."""
        width, height = size
        with self._lock:
            image, outputs, binding = self._binding(width, height)
            if rgb.shape[1::-1] != (width, height):
                shrink = width < rgb.shape[1]
                rgb = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
            for channel in range(3):  # (rgb / 255 - mean) / std, written straight into the bound input
                plane = image[0, channel]
                np.multiply(rgb[:, :, channel], np.float32(1 / (255 * IMAGENET_STD[channel])), out=plane,
                            casting="unsafe")
                plane -= IMAGENET_MEAN[channel] / IMAGENET_STD[channel]
            if binding is None:
                outputs = self.openvino({"image": image})
            else:
                self.session.run_with_iobinding(binding)
            return R2D2Maps(outputs["descriptors"][0], outputs["reliability"][0, 0],
                            outputs["repeatability"][0, 0], self.feature_stride)


def time_network(network: R2D2Network, rgb: np.ndarray, size: tuple[int, int], runs: int = 2) -> float:
    """The fastest of ``runs`` timed runs of ``network`` on ``rgb`` at ``size``, in ms, after one untimed run."""
    network(rgb, size)  # compiles for the size
    timed = []
    for _ in range(runs):
        t0 = time.perf_counter()
        network(rgb, size)
        timed.append((time.perf_counter() - t0) * 1000)
    return min(timed)
