"""The Siamese matcher on every keyframe network's descriptors (issue 41, item 4): two real frames 0.8 s apart,
each network's keypoints matched by the Siamese head, then PnP RANSAC on the first frame's depth. Every network
must give enough geometrically consistent matches, and the same relative pose as faster2d2's, which the Siamese head
was trained on."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from twohr.config import MatcherConfig
from twohr.dataset import RGBDSequence
from twohr.models import KEYFRAME_NETWORKS
from twohr_services.matcher.core import build_matcher

FIRST, SECOND = 120, 145  # 25 frames at 30 Hz: a person walks through this stretch


@pytest.fixture(scope="module")
def frames(dev_sequence):
    sequence = RGBDSequence(dev_sequence)
    return sequence.camera.matrix, sequence.read(FIRST), sequence.read(SECOND)


def relative_pose(network: str, frames, keyframe_networks) -> tuple[int, float, np.ndarray, np.ndarray]:
    """(PnP inliers, their share of the matches, rotation vector, translation) of the second frame in the first's
    camera, from ``network``'s keypoints (f32, no latency budget: the session's, which the detector's tests read
    too) matched by the Siamese head."""
    camera, first, _ = frames
    kp_a, kp_b = keyframe_networks.keypoints(network, FIRST), keyframe_networks.keypoints(network, SECOND)
    matches = build_matcher(MatcherConfig(method="siamese"))(kp_a.descriptors, kp_b.descriptors)
    xy_a, xy_b = kp_a.xy[matches.idx_a], kp_b.xy[matches.idx_b]
    depth = first.depth[np.round(xy_a[:, 1]).astype(int), np.round(xy_a[:, 0]).astype(int)]
    valid = depth > 0
    rays = np.linalg.inv(camera) @ np.vstack([xy_a[valid].T, np.ones(valid.sum())])
    points = (rays * depth[valid]).T
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(points.astype(np.float64), xy_b[valid].astype(np.float64), camera,
                                                 None, reprojectionError=3.0, iterationsCount=500,
                                                 flags=cv2.SOLVEPNP_EPNP, confidence=0.999)
    assert ok, f"{network}: PnP found no pose from {len(matches)} matches"
    return len(inliers), len(inliers) / len(matches), rvec.ravel(), tvec.ravel()


def test_the_siamese_matcher_gives_every_network_the_same_relative_pose(frames, keyframe_networks):
    poses = {network: relative_pose(network, frames, keyframe_networks) for network in KEYFRAME_NETWORKS}
    reference = poses["faster2d2"]
    # the camera moves about 10 cm and 3 degrees between the frames; the networks agree to a few millimetres
    assert reference[0] >= 150 and reference[1] >= 0.5 and np.linalg.norm(reference[3]) > 0.05
    for network, (inliers, share, rvec, tvec) in poses.items():
        rotation_deg = np.degrees(np.linalg.norm(cv2.Rodrigues(cv2.Rodrigues(rvec)[0].T
                                                               @ cv2.Rodrigues(reference[2])[0])[0]))
        assert inliers >= 100 and share >= 0.6 * reference[1], (network, inliers, share)
        assert rotation_deg < 0.5 and np.linalg.norm(tvec - reference[3]) < 0.015, (network, rotation_deg, tvec)
