"""A :class:`~.map.Map` to and from a map file (:mod:`twohr.mapfile`), with the checks that make it usable here:
the same detector model (its descriptors must match ours) and the same camera (the keypoints are its pixels)."""

from __future__ import annotations

import re
import time
from pathlib import Path

import numpy as np

from twohr.config import PipelineConfig
from twohr.dataset import CameraIntrinsics
from twohr.mapfile import NAME_PATTERN, MapFile, MapFileError, MapHeader, arrays_file, read_map, write_map

from .map import Map


def map_name(path: str | Path) -> str:
    """The name of the map a file holds: its file name without ``.map``; :class:`MapFileError` when unusable."""
    name = Path(path).name.removesuffix(".map")
    if not re.fullmatch(NAME_PATTERN, name) or re.search(r"\.v\d+$", name):
        raise MapFileError(f"{path}: a map's name (its file name without .map) must match {NAME_PATTERN}, not "
                           "ending in .v<number>")
    return name


def map_file(world: Map, config: PipelineConfig, name: str, built_by: str = "",
             parent: MapHeader | None = None) -> MapFile:
    """``world`` as a map file named ``name``, with what it was built with."""
    return arrays_file(world.arrays(), world.camera, config, name, built_by, parent)


def save_map(path: str | Path, world: Map, config: PipelineConfig, built_by: str = "",
             parent: MapHeader | None = None) -> tuple[MapHeader, int, float]:
    """Write ``world`` to ``path`` (atomically); returns its header, size in bytes and seconds taken."""
    start = time.perf_counter()
    stored = map_file(world, config, map_name(path), built_by, parent)
    size = write_map(path, stored)
    return stored.header, size, time.perf_counter() - start


def usable_map(stored: MapFile, config: PipelineConfig, camera: CameraIntrinsics, where: str = "map") -> Map:
    """A stored map as a :class:`Map` for this camera and config; :class:`MapFileError` (one line) when it was
    built with another detector or camera, or is empty."""
    header = stored.header
    header.check_built_with(config.detector, where)
    built_with = header.camera
    same = [built_with.width, built_with.height] == [camera.width, camera.height] and np.allclose(
        built_with.matrix, camera.matrix, atol=1e-6)
    if not same:
        raise MapFileError(f"{where}: built with another camera ({built_with.width}x{built_with.height}, fx "
                           f"{built_with.fx:g}); this one is {camera.width}x{camera.height}, fx {camera.fx:g}")
    if header.keyframes == 0:
        raise MapFileError(f"{where}: the map is empty (no keyframes)")
    return Map.from_arrays(camera, config.tracker, stored.arrays)


def load_map(path: str | Path, config: PipelineConfig, camera: CameraIntrinsics) -> tuple[Map, MapHeader, float]:
    """The map in ``path`` for a camera and config; returns it, its header and seconds taken.
    :class:`MapFileError` (one line) when the file is unusable, or was built with another detector model or camera."""
    start = time.perf_counter()
    stored = read_map(path)
    return usable_map(stored, config, camera, str(path)), stored.header, time.perf_counter() - start
