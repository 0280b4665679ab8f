"""The detector core: R2D2/L2-Net keypoints and the paper's 2HR filter. Arrays in, keypoints out.

Pipeline of :class:`R2D2Detector` (paper §3.1):

1. the network gives a 128-D descriptor map plus reliability and repeatability maps;
2. candidates are local maxima of repeatability (3x3 NMS) above the score floors;
3. the 2HR filter (:func:`twohr_filter`) clusters the candidates' reliability (k=3) and
   repeatability (k=2) with 1-D K-means, keeps the top cluster of each, intersects them and
   keeps composite scores ``s = reliability * repeatability > T``;
4. the top ``max_keypoints`` by composite score are kept, in original-image pixels.

:class:`ORBDetector` is the OpenCV ORB baseline with the same interface.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from functools import cache

import cv2
import numpy as np
import onnxruntime as ort

from twohr.config import DetectorConfig
from twohr.features import Keypoints
from twohr.models import model_path

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)


# ----------------------------------------------------------------------------- pure functions


def kmeans_1d(values: np.ndarray, k: int, iterations: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic 1-D K-means (Lloyd's algorithm, centres initialised at evenly spaced quantiles).

    Returns ``(labels, centres)`` with centres sorted ascending, so label ``k-1`` is the top cluster.
    """
    values = np.asarray(values, dtype=np.float64).ravel()
    if values.size == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    k = max(1, min(k, values.size))
    order = np.sort(values)
    centres = np.quantile(order, (np.arange(k) + 0.5) / k)
    for _ in range(iterations):
        # in 1-D the clusters are intervals: boundaries are midpoints between sorted centres
        bounds = (centres[1:] + centres[:-1]) / 2
        labels = np.searchsorted(bounds, order, side="right")
        sums = np.bincount(labels, weights=order, minlength=k)
        counts = np.bincount(labels, minlength=k)
        new = np.where(counts > 0, sums / np.maximum(counts, 1), centres)
        if np.allclose(new, centres, rtol=0, atol=1e-12):
            break
        centres = np.sort(new)
    bounds = (centres[1:] + centres[:-1]) / 2
    return np.searchsorted(bounds, values, side="right"), centres


def twohr_filter(reliability: np.ndarray, repeatability: np.ndarray, reliability_clusters: int = 3,
                 repeatability_clusters: int = 2, score_threshold: float = 0.5) -> np.ndarray:
    """The paper's 2HR selection: boolean mask of points in the top reliability cluster AND the top
    repeatability cluster whose composite score ``reliability * repeatability`` exceeds the threshold."""
    reliability = np.asarray(reliability, dtype=np.float64)
    repeatability = np.asarray(repeatability, dtype=np.float64)
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


def network_size(width: int, height: int, scale: float) -> tuple[int, int]:
    """Network input (width, height): the image scaled by ``scale`` and rounded to even numbers."""
    return max(2, int(round(width * scale / 2)) * 2), max(2, int(round(height * scale / 2)) * 2)


# ----------------------------------------------------------------------------- R2D2 network


@dataclass
class R2D2Maps:
    """Network outputs at network resolution: descriptors (128, h, w), reliability and repeatability (h, w).

    The arrays are views into reused buffers: copy them to keep them past the next call."""

    descriptors: np.ndarray
    reliability: np.ndarray
    repeatability: np.ndarray


@cache
def _session(path: str, threads: int) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return ort.InferenceSession(path, options, providers=["CPUExecutionProvider"])


class R2D2Network:
    """One onnxruntime session per process and model; input and output buffers reused per size."""

    def __init__(self, model: str = "faster2d2_WASF_N16", threads: int = 2) -> None:
        self.model = model
        self.session = _session(str(model_path(model, kind="r2d2")), threads)
        self._buffers: dict[tuple[int, int], tuple[np.ndarray, dict[str, np.ndarray], ort.IOBinding]] = {}
        self._lock = threading.Lock()

    def _binding(self, width: int, height: int):
        key = (width, height)
        if key not in self._buffers:
            image = np.zeros((1, 3, height, width), np.float32)
            outputs = {
                "descriptors": np.zeros((1, 128, height, width), np.float32),
                "reliability": np.zeros((1, 1, height, width), np.float32),
                "repeatability": np.zeros((1, 1, height, width), np.float32),
            }
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
            resized = rgb if rgb.shape[1::-1] == (width, height) else cv2.resize(
                rgb, (width, height), interpolation=cv2.INTER_AREA)
            normalised = (resized.astype(np.float32) * np.float32(1 / 255) - IMAGENET_MEAN) / IMAGENET_STD
            image[0] = normalised.transpose(2, 0, 1)
            self.session.run_with_iobinding(binding)
            return R2D2Maps(outputs["descriptors"][0], outputs["reliability"][0, 0], outputs["repeatability"][0, 0])


# ----------------------------------------------------------------------------- detectors


def _check_image(rgb: np.ndarray) -> None:
    if not isinstance(rgb, np.ndarray) or rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        shape = getattr(rgb, "shape", None)
        raise ValueError(f"expected an RGB uint8 image of shape (H, W, 3), got {shape} {getattr(rgb, 'dtype', '')}")


class R2D2Detector:
    """2HR (or raw R2D2) keypoints with 128-D float descriptors."""

    default_conf = DetectorConfig()

    def __init__(self, conf: DetectorConfig | None = None) -> None:
        self.conf = conf or self.default_conf
        self.network = R2D2Network(self.conf.model, self.conf.threads)

    def detect(self, rgb: np.ndarray) -> Keypoints:
        _check_image(rgb)
        conf = self.conf
        height, width = rgb.shape[:2]
        net_w, net_h = network_size(width, height, conf.input_scale)
        maps = self.network(rgb, (net_w, net_h))
        border = max(0, int(round(conf.border * net_w / width)))
        ys, xs = local_maxima(maps.repeatability, maps.reliability, conf.min_repeatability,
                              conf.min_reliability, border)
        rel = maps.reliability[ys, xs]
        rep = maps.repeatability[ys, xs]
        if conf.features == "2hr":
            keep = twohr_filter(rel, rep, conf.reliability_clusters, conf.repeatability_clusters,
                                conf.score_threshold)
            ys, xs, rel, rep = ys[keep], xs[keep], rel[keep], rep[keep]
        scores = rel * rep
        top = np.argsort(-scores, kind="stable")[: conf.max_keypoints]
        ys, xs, rel, rep, scores = ys[top], xs[top], rel[top], rep[top], scores[top]
        descriptors = np.ascontiguousarray(maps.descriptors[:, ys, xs].T)
        xy = np.stack([(xs + 0.5) * (width / net_w) - 0.5, (ys + 0.5) * (height / net_h) - 0.5], axis=1)
        return Keypoints(xy.astype(np.float32), descriptors, scores.astype(np.float32),
                         rel.astype(np.float32), rep.astype(np.float32))


class ORBDetector:
    """OpenCV ORB keypoints with 256-bit binary descriptors: the classical baseline."""

    default_conf = DetectorConfig(features="orb")

    def __init__(self, conf: DetectorConfig | None = None) -> None:
        self.conf = conf or self.default_conf
        self.orb = cv2.ORB_create(nfeatures=self.conf.max_keypoints)

    def detect(self, rgb: np.ndarray) -> Keypoints:
        _check_image(rgb)
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        kps, desc = self.orb.detectAndCompute(gray, None)
        if desc is None or not kps:
            return Keypoints.empty(dim=32, binary=True)
        xy = np.array([k.pt for k in kps], np.float32)
        scores = np.array([k.response for k in kps], np.float32)
        return Keypoints(xy, desc, scores)


def build_detector(conf: DetectorConfig) -> R2D2Detector | ORBDetector:
    """The detector that ``conf.features`` names."""
    return ORBDetector(conf) if conf.features == "orb" else R2D2Detector(conf)
