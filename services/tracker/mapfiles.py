"""A :class:`~.map.Map` to and from a map file (:mod:`twohr.mapfile`), with the checks that make it usable here:
the same detector model (its descriptors must match ours) and the same camera (the keypoints are its pixels)."""

from __future__ import annotations

import re
import time
from pathlib import Path

import numpy as np

from twohr import models
from twohr.config import PipelineConfig
from twohr.dataset import CameraIntrinsics
from twohr.errors import ModelError
from twohr.mapfile import NAME_PATTERN, MapFile, MapFileError, MapHeader, read_map, write_map

from .map import Map


def map_name(path: str | Path) -> str:
    """The name of the map a file holds: its file name without ``.map``; :class:`MapFileError` when unusable."""
    name = Path(path).name.removesuffix(".map")
    if not re.match(NAME_PATTERN, name):
        raise MapFileError(f"{path}: a map's name (its file name without .map) must match {NAME_PATTERN}")
    return name


def save_map(path: str | Path, world: Map, config: PipelineConfig, built_by: str = "",
             parent: MapHeader | None = None) -> tuple[MapHeader, int, float]:
    """Write ``world`` to ``path`` (atomically); returns its header, size in bytes and seconds taken."""
    start = time.perf_counter()
    arrays = world.arrays()
    try:
        sha256 = models.get_spec(config.detector.model).sha256
    except ModelError:
        sha256 = ""
    header = MapHeader(name=map_name(path), built_by=built_by,
                       parent=None if parent is None else f"{parent.name}@{parent.created:.3f}",
                       camera=world.camera, detector_model=config.detector.model, detector_sha256=sha256,
                       detector_config=config.detector.model_dump(mode="json"),
                       descriptor_dim=arrays.landmark_descriptors.shape[1],
                       descriptor_dtype=str(arrays.landmark_descriptors.dtype),
                       keyframes=len(arrays.keyframe_stamps), landmarks=len(arrays.landmark_positions))
    size = write_map(path, MapFile(header, arrays))
    return header, size, time.perf_counter() - start


def load_map(path: str | Path, config: PipelineConfig, camera: CameraIntrinsics) -> tuple[Map, MapHeader, float]:
    """The map in ``path`` for a camera and config; returns it, its header and seconds taken.
    :class:`MapFileError` (one line) when the file is unusable, or was built with another detector model or camera."""
    start = time.perf_counter()
    stored = read_map(path, detector_model=config.detector.model)
    built_with = stored.header.camera
    same = [getattr(built_with, k) for k in ("width", "height")] == [camera.width, camera.height] and np.allclose(
        built_with.matrix, camera.matrix, atol=1e-6)
    if not same:
        raise MapFileError(f"{path}: built with another camera ({built_with.width}x{built_with.height}, fx "
                           f"{built_with.fx:g}); this sequence's is {camera.width}x{camera.height}, fx {camera.fx:g}")
    if stored.header.keyframes == 0:
        raise MapFileError(f"{path}: the map is empty (no keyframes)")
    return Map.from_arrays(camera, config.tracker, stored.arrays), stored.header, time.perf_counter() - start

