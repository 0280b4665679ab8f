"""Matcher fixtures: a few held-out real frames of the Bonn dev sequence, detected once per session."""

from __future__ import annotations

import pytest

#: Held-out frames (the last 20 % of the 560 dev frames): pairs with gaps 2, 4, 6 and 10.
HELD_OUT_FRAMES = [500, 502, 506, 510]


@pytest.fixture(scope="session")
def held_out_cache(dev_sequence, tmp_path_factory):
    """A keypoint cache with 2HR keypoints of HELD_OUT_FRAMES (the detector's defaults, as in training)."""
    from twohr.config import DetectorConfig
    from twohr.dataset import RGBDSequence
    from twohr_lab.matching.data import KeypointCache
    from twohr_services.detector.core import build_detector

    conf = DetectorConfig(latency_budget_ms=None)  # input_scale on any machine
    cache = KeypointCache(RGBDSequence(dev_sequence), conf, tmp_path_factory.mktemp("matcher_cache"))
    cache.fill(HELD_OUT_FRAMES, build_detector(conf), progress=False)
    return cache


@pytest.fixture(scope="session")
def held_out_pairs() -> list[tuple[int, int]]:
    frames = HELD_OUT_FRAMES
    return [(a, b) for i, a in enumerate(frames) for b in frames[i + 1:]]
