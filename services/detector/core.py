"""The detector core: R2D2/L2-Net keypoints and the paper's 2HR filter. Arrays in, keypoints out.

Pipeline of :class:`R2D2Detector` (paper §3.1):

1. the network gives a 128-D feature map plus reliability and repeatability maps;
2. candidates are local maxima of repeatability (3x3 NMS) above the score floors;
3. the 2HR filter (:func:`twohr_filter`) clusters the candidates' reliability (k=3) and
   repeatability (k=2) with 1-D K-means, keeps the top cluster of each, intersects them and
   keeps composite scores ``s = reliability * repeatability > T``;
4. the top ``max_keypoints`` by composite score are kept, in original-image pixels, and only
   their descriptors are read from the feature map and L2-normalised.

:class:`ORBDetector`, :class:`FASTDetector` and :class:`SIFTDetector` are the OpenCV baselines with
the same interface.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import threading
import time
from bisect import bisect_right
from dataclasses import dataclass
from datetime import datetime, timezone
from functools import cache
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort
from pydantic import BaseModel, ValidationError

from twohr.config import DetectorConfig
from twohr.errors import ModelError
from twohr.features import Keypoints
from twohr.machine import machine
from twohr.mapfile import write_bytes_atomically
from twohr.models import (
    ORT_PROVIDERS,
    Network,
    auto_candidates,
    cache_dir,
    get_spec,
    keyframe_network,
    model_path,
    ort_session,
    resolve_backend,
)

log = logging.getLogger("twohr.detector")

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)
DESCRIPTOR_DIM = 128


# ----------------------------------------------------------------------------- pure functions


def kmeans_1d(values: np.ndarray, k: int, iterations: int = 300) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic 1-D K-means. Returns ``(labels, centres)``, centres ascending, so the top cluster is ``k-1``.

    In 1-D every cluster is an interval of the sorted values, so one Lloyd step is k binary searches
    and k differences of prefix sums: O(k log n), done on Python scalars because k is tiny. Two starts
    (centres at quantiles, centres evenly spread over the range) are run to convergence and the one
    with the lower sum of squared errors wins. Clusters may end up empty when there are fewer distinct
    values than ``k``.
    """
    values = np.asarray(values, dtype=np.float64).ravel()
    n = values.size
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    k = max(1, min(int(k), n))
    ordered = np.sort(values)
    sorted_list = ordered.tolist()
    prefix = [0.0, *np.cumsum(ordered).tolist()]
    prefix_sq = [0.0, *np.cumsum(ordered * ordered).tolist()]
    low, high = sorted_list[0], sorted_list[-1]
    starts = [
        [sorted_list[min(n - 1, int((i + 0.5) * n / k))] for i in range(k)],
        [low + (high - low) * (i + 1) / (k + 1) for i in range(k)],
    ]
    best_sse, best_centres = np.inf, sorted(starts[0])
    for centres in starts:
        centres = sorted(centres)
        edges: list[int] = []
        for _ in range(iterations):
            # values <= a midpoint go to the lower cluster
            midpoints = [(a + b) / 2 for a, b in zip(centres, centres[1:], strict=False)]
            new_edges = [0, *(bisect_right(sorted_list, m) for m in midpoints), n]
            if new_edges == edges:
                break
            edges = new_edges
            centres = sorted((prefix[e1] - prefix[e0]) / (e1 - e0) if e1 > e0 else c
                             for e0, e1, c in zip(edges, edges[1:], centres, strict=False))
        sse = sum(prefix_sq[e1] - prefix_sq[e0] - (prefix[e1] - prefix[e0]) ** 2 / (e1 - e0)
                  for e0, e1 in zip(edges, edges[1:], strict=False) if e1 > e0)
        if sse < best_sse - 1e-12:
            best_sse, best_centres = sse, centres
    centres_array = np.array(best_centres)
    labels = np.searchsorted((centres_array[1:] + centres_array[:-1]) / 2, values, side="left")
    return labels.astype(np.int64), centres_array


def twohr_filter(reliability: np.ndarray, repeatability: np.ndarray, reliability_clusters: int = 3,
                 repeatability_clusters: int = 2, score_threshold: float = 0.5) -> np.ndarray:
    """The paper's 2HR selection: boolean mask of points in the top reliability cluster AND the top
    repeatability cluster whose composite score ``reliability * repeatability`` exceeds the threshold.

    The top cluster is the non-empty cluster with the highest centre.
    """
    reliability = np.asarray(reliability, dtype=np.float64).ravel()
    repeatability = np.asarray(repeatability, dtype=np.float64).ravel()
    if reliability.shape != repeatability.shape:
        raise ValueError(f"reliability and repeatability differ in length: {reliability.size} vs {repeatability.size}")
    if reliability.size == 0:
        return np.zeros(0, bool)
    rel_labels, _ = kmeans_1d(reliability, reliability_clusters)
    rep_labels, _ = kmeans_1d(repeatability, repeatability_clusters)
    top_rel = rel_labels == rel_labels.max()
    top_rep = rep_labels == rep_labels.max()
    return top_rel & top_rep & (reliability * repeatability > score_threshold)


def local_maxima(repeatability: np.ndarray, reliability: np.ndarray, min_repeatability: float,
                 min_reliability: float, border: int) -> tuple[np.ndarray, np.ndarray]:
    """(ys, xs) of 3x3 local maxima of repeatability that pass both score floors, away from the border."""
    dilated = cv2.dilate(repeatability, np.ones((3, 3), np.uint8))
    peak = (repeatability == dilated) & (repeatability >= min_repeatability) & (reliability >= min_reliability)
    if border > 0:
        peak[:border] = peak[-border:] = False
        peak[:, :border] = peak[:, -border:] = False
    return np.nonzero(peak)


def subpixel_offsets(score: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel offsets (dy, dx) in [-0.5, 0.5] of peaks (ys, xs) of ``score``: the vertex of a parabola through
    the peak and its two neighbours, per axis. Peaks on the map's border keep offset 0 on that axis."""
    height, width = score.shape
    offsets = []
    for axis, (index, size) in enumerate(((ys, height), (xs, width))):
        inner = (index > 0) & (index < size - 1)
        lo, hi = np.where(inner, index - 1, index), np.where(inner, index + 1, index)
        before = score[lo, xs] if axis == 0 else score[ys, lo]
        after = score[hi, xs] if axis == 0 else score[ys, hi]
        centre = score[ys, xs]
        curvature = before.astype(np.float64) - 2 * centre + after
        # a true maximum curves down; a flat or inverted neighbourhood says nothing below a pixel
        safe = inner & (curvature < -1e-9)
        offset = np.where(safe, 0.5 * (before - after) / np.where(safe, curvature, -1.0), 0.0)
        offsets.append(np.clip(offset, -0.5, 0.5))
    return offsets[0], offsets[1]


def select_keypoints(reliability: np.ndarray, repeatability: np.ndarray, conf: DetectorConfig) -> np.ndarray:
    """Indices of the candidates (already local maxima) that ``conf`` keeps, best composite score first.

    Applies the score floors, the 2HR filter when ``conf.features == "2hr"`` and the top-N cut.
    """
    floors = (reliability >= conf.min_reliability) & (repeatability >= conf.min_repeatability)
    index = np.flatnonzero(floors)
    if conf.features == "2hr" and index.size:
        keep = twohr_filter(reliability[index], repeatability[index], conf.reliability_clusters,
                            conf.repeatability_clusters, conf.score_threshold)
        index = index[keep]
    scores = reliability[index] * repeatability[index]
    return index[np.argsort(-scores, kind="stable")[: conf.max_keypoints]]


def network_size(width: int, height: int, scale: float) -> tuple[int, int]:
    """Network input (width, height): the image scaled by ``scale`` and rounded to even numbers."""
    return max(2, int(round(width * scale / 2)) * 2), max(2, int(round(height * scale / 2)) * 2)


def choose_input_scale(latency_ms: float, measured_at: float, budget_ms: float, largest: float,
                       smallest: float, step: float = 0.125) -> float:
    """The largest of ``largest``, ``largest - step``, ... down to ``smallest`` whose latency fits ``budget_ms``,
    predicted from ``latency_ms`` timed at scale ``measured_at`` by the pixel count (a convolutional network's cost
    grows with it: here within 4 % of the timed latency from 0.5 to 0.75); the last step above ``smallest`` when
    none fits."""
    scale = largest
    while scale - step >= smallest - 1e-9 and latency_ms * (scale / measured_at) ** 2 > budget_ms:
        scale -= step
    return scale


# ----------------------------------------------------------------------------- R2D2 network


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


# ----------------------------------------------------------------------------- detectors


def check_image(rgb: np.ndarray) -> None:
    """Raise a clear ValueError unless ``rgb`` is an (H, W, 3) uint8 image of at least 16x16 pixels."""
    if not isinstance(rgb, np.ndarray):
        raise ValueError(f"expected an RGB uint8 numpy image of shape (H, W, 3), got {type(rgb).__name__}")
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"expected an RGB uint8 image of shape (H, W, 3), got shape {rgb.shape} dtype {rgb.dtype}")
    if min(rgb.shape[:2]) < 16:
        raise ValueError(f"image too small for keypoint detection: {rgb.shape[1]}x{rgb.shape[0]} (need 16x16)")


#: ``auto`` keeps the best-quality candidate within this factor of the fastest (timing noise on a shared machine)
AUTO_TIE = 1.05


def auto_choices_path() -> Path:
    """Where ``detector.model=auto`` keeps its choices on this host (``$TWOHR_CACHE/models/auto-choices.json``);
    delete it, or run ``twohr models auto --again``, to time the candidates again."""
    return cache_dir() / "auto-choices.json"


class AutoChoice(BaseModel):
    """One ``auto`` choice: the network kept, each candidate's timed latency and when it was timed."""

    model: str
    timings_ms: dict[str, float]
    timed_at: str


def auto_choice_key(conf: DetectorConfig, candidates: list[str], size: tuple[int, int]) -> str:
    """What an ``auto`` choice depends on: the CPU, the backend, precision and threads, the timing size, and each
    candidate's exact bytes (a new model version is timed again)."""
    cpu = machine()
    networks = ",".join(f"{name}@{get_spec(name).sha256[:12]}" for name in candidates)
    return (f"{cpu['cpu_model']} x{cpu['cpus']} | {resolve_backend(conf.backend)} {conf.precision} "
            f"threads={conf.threads} | {size[0]}x{size[1]} | {networks}")


def read_auto_choices(path: Path) -> dict[str, AutoChoice]:
    """The choices kept in ``path``; an absent, unreadable or malformed file holds none (they are timed again)."""
    try:
        raw = json.loads(path.read_text())
        return {key: AutoChoice.model_validate(value) for key, value in raw.items()}
    except FileNotFoundError:
        return {}
    except (OSError, ValueError, ValidationError, AttributeError) as exc:
        log.warning("detector.model=auto ignores %s (%s); it times the networks again", path, exc)
        return {}


@contextlib.contextmanager
def auto_choice_lock(path: Path):
    """Hold the host's ``auto`` lock: replicas that start together time one after the other (undisturbed by each
    other) and the later ones find the first one's choice. A cache without write access goes without the lock."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle = open(path.with_suffix(".lock"), "a")
    except OSError:
        yield
        return
    with handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def keep_auto_choice(path: Path, key: str, choice: AutoChoice) -> None:
    """Add ``choice`` under ``key`` to ``path`` (atomically); a read-only cache only costs a warning."""
    choices = read_auto_choices(path)
    choices[key] = choice
    data = json.dumps({k: v.model_dump() for k, v in choices.items()}, indent=1).encode()
    try:
        write_bytes_atomically(path, data)
    except OSError as exc:
        log.warning("detector.model=auto cannot keep its choice in %s (%s): every process times again", path, exc)


class R2D2Detector:
    """2HR (or raw R2D2) keypoints with 128-D float descriptors.

    ``conf.model`` names the network (a short name of :data:`twohr.models.KEYFRAME_NETWORKS` or a registered
    r2d2-kind model), or ``auto``: every network whose measured feature quality meets the floor
    (:func:`twohr.models.auto_candidates`) is timed once per host, and the fastest is kept (``model``,
    ``model_timings_ms``) in ``auto_choices`` (default :func:`auto_choices_path`). Every later process on the host
    reads that choice instead of timing again, so processes that must agree (replicas, ``twohr run`` and the
    services) use one network, whatever load each started under.
    """

    default_conf = DetectorConfig()

    def __init__(self, conf: DetectorConfig | None = None, auto_choices: Path | None = None) -> None:
        self.conf = conf or self.default_conf
        self.auto_choices = auto_choices or auto_choices_path()
        """where ``auto`` keeps its choices on this host"""
        if self.conf.features not in ("2hr", "r2d2"):
            raise ValueError(f"R2D2Detector builds 2hr or r2d2 features, not {self.conf.features!r}")
        resolve_backend(self.conf.backend)  # a backend this machine lacks fails here, before any image
        self.model: str | None = None if self.conf.model == "auto" else keyframe_network(self.conf.model)
        """the registered network in use (None until ``auto`` has chosen)"""
        self.model_timings_ms: dict[str, float] = {}
        """each timed network's latency at ``min_input_scale`` (the basis of ``auto``)"""
        self.model_timed_at: str | None = None
        """when ``auto`` timed them (UTC, ISO 8601); earlier than this process where the choice was kept"""
        self._network: R2D2Network | None = None if self.model is None else self._open(self.model)
        self.input_scales: dict[tuple[int, int], float] = {}
        """image (width, height) -> the input scale chosen for it (see ``latency_budget_ms``)"""

    def _open(self, model: str) -> R2D2Network:
        return R2D2Network(model, self.conf.threads, backend=self.conf.backend, precision=self.conf.precision)

    @property
    def network(self) -> R2D2Network:
        """The network in use; ``auto`` chooses it now if no image has yet (timed on a blank VGA image: a
        convolutional network's time does not depend on the pixels)."""
        if self._network is None:
            self._choose_model(np.zeros((480, 640, 3), np.uint8), network_size(640, 480, self.conf.min_input_scale))
        return self._network

    def _time(self, network: R2D2Network, rgb: np.ndarray, size: tuple[int, int], runs: int = 2) -> float:
        network(rgb, size)  # compiles for the size
        timed = []
        for _ in range(runs):
            t0 = time.perf_counter()
            network(rgb, size)
            timed.append((time.perf_counter() - t0) * 1000)
        return min(timed)

    def _choose_model(self, rgb: np.ndarray, size: tuple[int, int]) -> float:
        """``auto``: the network kept on this host for ``size``, else time every candidate
        (:func:`twohr.models.auto_candidates`) on ``rgb`` at ``size`` and keep the fastest. Returns its latency."""
        candidates = auto_candidates()
        key = auto_choice_key(self.conf, candidates, size)
        with auto_choice_lock(self.auto_choices):
            kept = read_auto_choices(self.auto_choices).get(key)
            if kept is not None and kept.model in candidates and kept.model in kept.timings_ms:
                try:
                    self._network = self._open(kept.model)
                except (ModelError, OSError) as exc:
                    log.warning("detector.model=auto cannot load %s, its choice on this host: %s", kept.model, exc)
                else:
                    self.model, self.model_timings_ms, self.model_timed_at = kept.model, kept.timings_ms, kept.timed_at
                    log.info("detector.model=auto uses %s, chosen on this host at %s (%s)", self.model,
                             kept.timed_at, self.auto_choices)
                    return self.model_timings_ms[self.model]
            self._time_candidates(candidates, rgb, size)
            if set(self.model_timings_ms) == set(candidates):  # a choice made without some candidate is not kept
                keep_auto_choice(self.auto_choices, key, AutoChoice(
                    model=self.model, timings_ms=self.model_timings_ms, timed_at=self.model_timed_at))
        return self.model_timings_ms[self.model]

    def _time_candidates(self, candidates: list[str], rgb: np.ndarray, size: tuple[int, int]) -> None:
        networks = {}
        for name in candidates:
            try:
                networks[name] = self._open(name)
            except (ModelError, OSError) as exc:  # e.g. a mirror without that file, a read-only cache
                log.warning("detector.model=auto leaves out %s: %s", name, exc)
        if not networks:
            raise ModelError("detector.model=auto found no network it can load; run `twohr models fetch`")
        # kept for every later process on this host: worth a few more runs than one process's own scale choice
        self.model_timings_ms = {name: self._time(net, rgb, size, runs=5) for name, net in networks.items()}
        self.model_timed_at = datetime.now(timezone.utc).isoformat(timespec="seconds")
        fastest = min(self.model_timings_ms.values())
        # near-ties go to the earlier (better) network, so that timing noise does not flip the choice run to run
        self.model = next(n for n, ms in self.model_timings_ms.items() if ms <= AUTO_TIE * fastest)
        self._network = networks[self.model]
        log.info("detector.model=auto chose %s (%s at %dx%d)", self.model,
                 ", ".join(f"{n} {t:.0f} ms" for n, t in self.model_timings_ms.items()), *size)

    def input_scale(self, rgb: np.ndarray) -> float:
        """The network's input scale for images the size of ``rgb``: ``input_scale``, or with a latency budget the
        scale chosen by timing the network on ``rgb`` at ``min_input_scale`` the first time this size is seen
        (three runs at the smallest size: about 0.8 s on a slow CPU, where that is the scale it keeps)."""
        height, width = rgb.shape[:2]
        if (width, height) not in self.input_scales:
            scale, smallest = self.conf.input_scale, self.conf.min_input_scale
            size = network_size(width, height, smallest)
            timed = self._choose_model(rgb, size) if self._network is None else None  # auto: timed at this size
            if self.conf.latency_budget_ms is not None and scale > smallest:
                latency = timed or self._time(self.network, rgb, size)
                scale = choose_input_scale(latency, smallest, self.conf.latency_budget_ms, scale, smallest)
                log.info("%s at %dx%d: %.0f ms at input scale %g, %g chosen for the %.0f ms budget",
                         self.model, width, height, latency, smallest, scale, self.conf.latency_budget_ms)
            self.input_scales[(width, height)] = scale
        return self.input_scales[(width, height)]

    def detect(self, rgb: np.ndarray) -> Keypoints:
        """Keypoints of an RGB uint8 image, in its pixel coordinates, best score first."""
        check_image(rgb)
        height, width = rgb.shape[:2]
        maps = self.network(rgb, network_size(width, height, self.input_scale(rgb)))
        return self.keypoints_from_maps(maps, (width, height))

    def keypoints_from_maps(self, maps: R2D2Maps, image_size: tuple[int, int]) -> Keypoints:
        """Steps 2-4 of the pipeline on network outputs for an image of ``image_size`` = (width, height)."""
        width, height = image_size
        net_h, net_w = maps.repeatability.shape
        border = max(0, int(round(self.conf.border * net_w / width)))
        ys, xs = local_maxima(maps.repeatability, maps.reliability, self.conf.min_repeatability,
                              self.conf.min_reliability, border)
        rel = maps.reliability[ys, xs]
        rep = maps.repeatability[ys, xs]
        keep = select_keypoints(rel, rep, self.conf)
        ys, xs, rel, rep = ys[keep], xs[keep], rel[keep], rep[keep]
        dy, dx = subpixel_offsets(maps.repeatability, ys, xs) if self.conf.subpixel else (0.0, 0.0)
        xy = np.stack([(xs + dx + 0.5) * (width / net_w) - 0.5, (ys + dy + 0.5) * (height / net_h) - 0.5], axis=1)
        if self.conf.subpixel:  # a refined peak may not move into the border it was kept away from
            xy = np.clip(xy, self.conf.border, np.array([width, height]) - 1 - self.conf.border)
        return Keypoints(xy.astype(np.float32), maps.descriptors_at(ys, xs), (rel * rep).astype(np.float32),
                         rel.astype(np.float32), rep.astype(np.float32))


class ORBDetector:
    """OpenCV ORB keypoints with 256-bit binary descriptors: the classical baseline."""

    default_conf = DetectorConfig(features="orb")

    def __init__(self, conf: DetectorConfig | None = None) -> None:
        self.conf = conf or self.default_conf
        self.orb = cv2.ORB_create(nfeatures=self.conf.max_keypoints)

    def detect(self, rgb: np.ndarray) -> Keypoints:
        """ORB keypoints and descriptors of an RGB uint8 image."""
        check_image(rgb)
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        kps, desc = self.orb.detectAndCompute(gray, None)
        return _opencv_keypoints(kps, desc, dim=32, binary=True)


class FASTDetector:
    """OpenCV FAST corners (strongest ``max_keypoints`` after NMS) described by ORB, since FAST has no descriptor."""

    default_conf = DetectorConfig(features="fast")

    def __init__(self, conf: DetectorConfig | None = None) -> None:
        self.conf = conf or self.default_conf
        self.fast = cv2.FastFeatureDetector_create(threshold=20, nonmaxSuppression=True)
        self.orb = cv2.ORB_create(nfeatures=self.conf.max_keypoints)

    def detect(self, rgb: np.ndarray) -> Keypoints:
        """FAST corners with ORB descriptors (corners too close to the border for ORB are dropped)."""
        check_image(rgb)
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        kps = sorted(self.fast.detect(gray, None), key=lambda k: -k.response)[: self.conf.max_keypoints]
        kps, desc = self.orb.compute(gray, kps)
        return _opencv_keypoints(kps, desc, dim=32, binary=True)


class SIFTDetector:
    """OpenCV SIFT keypoints with 128-D descriptors, L2-normalised to float32 like R2D2's."""

    default_conf = DetectorConfig(features="sift")

    def __init__(self, conf: DetectorConfig | None = None) -> None:
        self.conf = conf or self.default_conf
        self.sift = cv2.SIFT_create(nfeatures=self.conf.max_keypoints)

    def detect(self, rgb: np.ndarray) -> Keypoints:
        """SIFT keypoints and unit descriptors of an RGB uint8 image."""
        check_image(rgb)
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        kps, desc = self.sift.detectAndCompute(gray, None)
        if desc is not None:
            desc = desc / np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
        return _opencv_keypoints(kps, desc, dim=128, binary=False)


def _opencv_keypoints(kps, desc: np.ndarray | None, dim: int, binary: bool) -> Keypoints:
    if desc is None or not kps:
        return Keypoints.empty(dim=dim, binary=binary)
    xy = np.array([k.pt for k in kps], np.float32)
    scores = np.array([k.response for k in kps], np.float32)
    return Keypoints(xy, desc.astype(np.uint8 if binary else np.float32), scores)


Detector = R2D2Detector | ORBDetector | FASTDetector | SIFTDetector


def build_detector(conf: DetectorConfig) -> Detector:
    """The detector that ``conf.features`` names."""
    classical = {"orb": ORBDetector, "fast": FASTDetector, "sift": SIFTDetector}
    return classical.get(conf.features, R2D2Detector)(conf)
