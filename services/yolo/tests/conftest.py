"""Fixtures of the yolo tests: real frames of the dev sequence and one detector per model."""

from __future__ import annotations

import pytest

from twohr.config import YoloConfig
from twohr.dataset import RGBDSequence


@pytest.fixture(scope="session")
def dev_frames(dev_sequence):
    """Read a dev frame once per session: ``dev_frames(index) -> Frame``."""
    seq = RGBDSequence(dev_sequence)
    cache = {}

    def read(index: int):
        if index not in cache:
            cache[index] = seq.read(index)
        return cache[index]

    return read


@pytest.fixture(scope="session")
def yolo_detector():
    """``yolo_detector(model) -> YoloDetector``, one per model for the session."""
    from twohr_services.yolo.core import YoloDetector

    detectors = {}

    def get(model: str = "yolov8n_320"):
        if model not in detectors:
            detectors[model] = YoloDetector(YoloConfig(model=model))
        return detectors[model]

    return get
