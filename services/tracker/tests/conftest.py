"""Fixtures of the tracker tests: ORB keypoints of the synthetic sequences, detected once per session.

Keypoints on the moving occluder are dropped with the sequence's exact ``dynamic/`` masks (the tests are
about the tracker, not the masker); the real-data test uses person boxes instead.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from twohr.config import DetectorConfig
from twohr.dataset import CameraIntrinsics, RGBDSequence
from twohr.features import Keypoints, Matches
from twohr.trajectory import Trajectory


@dataclass
class DetectedSequence:
    camera: CameraIntrinsics
    ground_truth: Trajectory
    stamps: list[float]
    keypoints: list[Keypoints]
    depths: list[np.ndarray]
    match: Callable[[np.ndarray, np.ndarray], Matches]


def hamming_mutual_nn(desc_a: np.ndarray, desc_b: np.ndarray) -> Matches:
    """Mutual nearest neighbours of packed binary descriptors (OpenCV brute force with cross-check)."""
    if len(desc_a) == 0 or len(desc_b) == 0:
        return Matches.empty()
    found = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(desc_a, desc_b)
    return Matches(np.array([m.queryIdx for m in found], np.int64), np.array([m.trainIdx for m in found], np.int64),
                   -np.array([m.distance for m in found], np.float32))


def detect_sequence(root: Path, max_keypoints: int = 400) -> DetectedSequence:
    from twohr_services.detector.core import ORBDetector

    sequence = RGBDSequence(root)
    detector = ORBDetector(DetectorConfig(features="orb", max_keypoints=max_keypoints))
    stamps, keypoints, depths = [], [], []
    for frame in sequence.frames():
        kps = detector.detect(frame.rgb)
        dynamic = cv2.imread(str(root / "dynamic" / f"{frame.stamp:.6f}.png"), cv2.IMREAD_GRAYSCALE) > 0
        u = np.clip(np.rint(kps.xy[:, 0]).astype(int), 0, dynamic.shape[1] - 1)
        v = np.clip(np.rint(kps.xy[:, 1]).astype(int), 0, dynamic.shape[0] - 1)
        stamps.append(frame.stamp)
        keypoints.append(kps.subset(~dynamic[v, u]))
        depths.append(frame.depth)
    return DetectedSequence(sequence.camera, sequence.ground_truth(), stamps, keypoints, depths,
                            hamming_mutual_nn)


@pytest.fixture(scope="session")
def orb_synthetic(synthetic_sequence) -> DetectedSequence:
    """The 60-frame synthetic sequence with one moving occluder, as masked ORB keypoints and depth."""
    return detect_sequence(synthetic_sequence)


@pytest.fixture(scope="session")
def orb_synthetic_other_room(tmp_path_factory) -> DetectedSequence:
    """20 synthetic frames of another room (another texture), as ORB keypoints and depth."""
    from twohr.synthetic import SyntheticSpec, generate

    return detect_sequence(generate(tmp_path_factory.mktemp("synth") / "other_room", SyntheticSpec(frames=20, seed=7)))


@pytest.fixture(scope="session")
def orb_real_frames(dev_sequence) -> DetectedSequence:
    """Every 3rd of the first 90 real Bonn frames (few people in view yet), as ORB keypoints and depth."""
    from twohr_services.detector.core import ORBDetector

    sequence = RGBDSequence(dev_sequence)
    detector = ORBDetector(DetectorConfig(features="orb", max_keypoints=800))
    stamps, keypoints, depths = [], [], []
    for frame in sequence.frames(0, 90, 3):
        stamps.append(frame.stamp)
        keypoints.append(detector.detect(frame.rgb))
        depths.append(frame.depth)
    return DetectedSequence(sequence.camera, sequence.ground_truth(sequence.default_gt_extrinsic()), stamps,
                            keypoints, depths, hamming_mutual_nn)
