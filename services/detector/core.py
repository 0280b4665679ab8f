"""The detector core, the room's face: :func:`build_detector` and :class:`R2D2Detector`. Arrays in, keypoints out.

Pipeline of :class:`R2D2Detector` (paper §3.1):

1. the network (:mod:`.networks`) gives a 128-D feature map plus reliability and repeatability maps;
2. candidates are local maxima of repeatability (3x3 NMS) above the score floors;
3. the 2HR filter (:func:`~.filter.twohr_filter`) clusters the candidates' reliability (k=3) and
   repeatability (k=2) with 1-D K-means, keeps the top cluster of each, intersects them and
   keeps composite scores ``s = reliability * repeatability > T``;
4. the top ``max_keypoints`` by composite score are kept, in original-image pixels, and only
   their descriptors are read from the feature map and L2-normalised.

``detector.model=auto`` picks the network in :mod:`.auto`. :class:`ORBDetector`, :class:`FASTDetector` and
:class:`SIFTDetector` (:mod:`.classic`) are the OpenCV baselines with the same interface.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from twohr.config import DetectorConfig
from twohr.features import Keypoints
from twohr.models import keyframe_network, resolve_backend

from .auto import auto_choices_path, choose_network
from .classic import FASTDetector, ORBDetector, SIFTDetector
from .filter import local_maxima, select_keypoints, subpixel_offsets
from .images import check_image, network_size
from .networks import R2D2Maps, R2D2Network, time_network

log = logging.getLogger("twohr.detector")


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


class R2D2Detector:
    """2HR (or raw R2D2) keypoints with 128-D float descriptors.

    ``conf.model`` names the network (a short name of :data:`twohr.models.KEYFRAME_NETWORKS` or a registered
    r2d2-kind model), or ``auto``: every network whose measured feature quality meets the floor
    (:func:`twohr.models.auto_candidates`) is timed once per host, and the fastest is kept (``model``,
    ``model_timings_ms``) in ``auto_choices`` (default :func:`~.auto.auto_choices_path`). Every later process on
    the host reads that choice instead of timing again, so processes that must agree (replicas, ``twohr run`` and
    the services) use one network, whatever load each started under.
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

    def _choose_model(self, rgb: np.ndarray, size: tuple[int, int]) -> float:
        """``auto``: the network kept on this host for ``size``, else the fastest candidate timed on ``rgb`` at
        ``size`` (:func:`~.auto.choose_network`). Returns its latency."""
        choice, self._network = choose_network(self.conf, self.auto_choices, rgb, size, self._open)
        self.model, self.model_timings_ms, self.model_timed_at = choice.model, choice.timings_ms, choice.timed_at
        return self.model_timings_ms[self.model]

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
                latency = timed or time_network(self.network, rgb, size)
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


Detector = R2D2Detector | ORBDetector | FASTDetector | SIFTDetector


def build_detector(conf: DetectorConfig) -> Detector:
    """The detector that ``conf.features`` names."""
    classical = {"orb": ORBDetector, "fast": FASTDetector, "sift": SIFTDetector}
    return classical.get(conf.features, R2D2Detector)(conf)
