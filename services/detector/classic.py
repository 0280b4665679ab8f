"""The classic path: OpenCV's ORB, FAST (described by ORB) and SIFT keypoints, the baselines with the same
``detect(rgb) -> Keypoints`` interface as :class:`~.core.R2D2Detector`. No network."""

from __future__ import annotations

import cv2
import numpy as np

from twohr.config import DetectorConfig
from twohr.features import Keypoints

from .images import check_image


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
