"""The map file: one self-describing file per map, that a robot can come back to and another robot can load.

A map file is a zip archive (``.map``) of ``header.json`` (:class:`MapHeader`: format and version, the map's name
and frame, the camera, the detector model and config it was built with, counts, provenance) and one ``.npy`` array
per field of :class:`MapArrays`, read with ``allow_pickle=False``. Keyframes keep their pose, stamp and keypoints
(pixels, depth, the landmark each one observes); a keypoint that observes a landmark has that landmark's
descriptor, the only descriptors a map keeps (those of unmatched keypoints are dropped, as in memory).

Written atomically (:func:`twohr.files.write_atomic`: a temporary file beside the target, fsync, rename).
:func:`read_map` checks everything and answers a wrong, corrupt or inconsistent file, or one built with another
detector model, with one :class:`MapFileError` line; :func:`read_header` reads the header alone. Plain arrays and
pydantic only: the tracker, the map room, the gateway and the CLI all use it.

Format version 2 adds the map's owners (:attr:`MapHeader.owners`: who built it first) and contributors (who changed
it under a grant: a record, no right); a version-1 file still loads, owned by the operator. A folder of maps with
their versions, and who may change them, is the map store (:mod:`twohr.mapstore`).
"""

from __future__ import annotations

import io
import json
import re
import time
import zipfile
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from .config import DetectorConfig, PipelineConfig
from .dataset import CameraIntrinsics
from .errors import ModelError, TwohrError, validation_problems
from .files import write_atomic
from .keys import ROBOT_PATTERN
from .models import descriptor_space, get_spec

FORMAT = "twohr-map"
VERSION = 3
#: the format versions this twohr reads (version 1 has no owners: the operator's)
READS = (1, 2, 3)
SUFFIX = ".map"
NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"
#: the operator's identity among a map's owners (a robot id cannot start with '@')
OPERATOR = "@operator"


class MapFileError(TwohrError):
    """A map file that cannot be used: missing, corrupt, of another format or version, inconsistent, or built with
    another detector model than the one asked for."""


def check_owner(identity: str) -> str:
    """``identity`` if it can own a map (a robot id, or :data:`OPERATOR`); ValueError otherwise."""
    if identity != OPERATOR and not re.fullmatch(ROBOT_PATTERN.pattern, identity):
        raise ValueError(f"{identity!r} is neither a robot id nor {OPERATOR}")
    return identity


class MapHeader(BaseModel):
    """What a map is and how it was built (``header.json``)."""

    model_config = ConfigDict(extra="forbid")

    format: str = FORMAT
    version: int = VERSION
    name: str = Field(pattern=NAME_PATTERN, description="the map's name, also the frame id of poses in it")
    created: float = Field(default_factory=time.time, description="Unix time it was written")
    built_by: str = Field("", description="the run or session that built it")
    owners: list[str] = Field(default_factory=lambda: [OPERATOR], min_length=1, description="the identities that "
                              f"built it (robot ids; {OPERATOR} for the operator's uploads and runs): a robot may "
                              "build or extend the map only when it is one of them or holds the operator's grant")
    contributors: list[str] = Field(default_factory=list, description="the identities that changed it without "
                                    "owning it (a robot under the operator's grant, the operator): a record, no "
                                    "right; a robot among them needs the grant again for its next change")
    parent: str | None = Field(None, description="the map it extends (name@created), if any")
    camera: CameraIntrinsics
    detector_model: str = Field(description="the 2HR detector model its descriptors come from")
    detector_sha256: str = Field("", description="the file checksum of the network of its descriptor space")
    detector_config: dict = Field(default_factory=dict, description="the detector config it was built with")
    descriptor_dim: int = Field(gt=0)
    descriptor_dtype: str
    keyframes: int = Field(ge=0)
    landmarks: int = Field(ge=0)
    cameras: list[CameraIntrinsics] = Field(default_factory=list, description="the cameras of keyframes taken with "
                                            "another camera than `camera` (a map built by several robots): "
                                            "keyframe_camera 1 is the first of them")
    camera_robots: list[str] = Field(default_factory=list, description="a shared map's: the robot whose keyframes "
                                     "each camera took (`camera` first), '' where not recorded")

    @field_validator("owners", "contributors")
    @classmethod
    def _known_owners(cls, owners: list[str]) -> list[str]:
        return list(dict.fromkeys(check_owner(owner) for owner in owners))  # once each, in the order they came

    @property
    def frame_id(self) -> str:
        """The frame of poses in this map: its name."""
        return self.name

    def check_built_with(self, detector: DetectorConfig, where: str = "map") -> None:
        """:class:`MapFileError` unless the map's descriptors come from the same descriptor space
        (:func:`twohr.models.descriptor_space`) and features as ``detector`` would give (other descriptors would not
        match them)."""
        built = (self.detector_model, self.detector_config.get("features", detector.features))
        if (descriptor_space(built[0]), built[1]) != (descriptor_space(detector.model), detector.features):
            raise MapFileError(f"{where}: built with detector {built[0]!r} ({built[1]} features), this run uses "
                               f"{detector.model!r} ({detector.features} features); its descriptors would not match")


@dataclass
class MapArrays:
    """Every array of a map, by its file name in the archive. Keypoints of all keyframes are stored back to back;
    ``keyframe_first[k]`` is where keyframe ``k``'s begin (and ``keyframe_first[K]`` the total)."""

    keyframe_poses: np.ndarray  # (K, 4, 4) float64 camera-to-world
    keyframe_stamps: np.ndarray  # (K,) float64
    keyframe_culled: np.ndarray  # (K,) bool
    keyframe_first: np.ndarray  # (K + 1,) int64
    keypoint_xy: np.ndarray  # (P, 2) float32 pixels
    keypoint_depth: np.ndarray  # (P,) float32 metres
    keypoint_landmark: np.ndarray  # (P,) int64, -1 = none
    landmark_positions: np.ndarray  # (L, 3) float64 world
    landmark_descriptors: np.ndarray  # (L, D)
    landmark_accepted: np.ndarray  # (L,) int64
    landmark_rejected: np.ndarray  # (L,) int64
    landmark_bad: np.ndarray  # (L,) bool
    keyframe_camera: np.ndarray | None = None
    """(K,) int64: 0 for the header's ``camera``, i for its ``cameras[i - 1]`` (None: every keyframe's is 0; the
    maps of format 2 and before have no such array)"""

    def __post_init__(self) -> None:
        if self.keyframe_camera is None:
            self.keyframe_camera = np.zeros(len(self.keyframe_stamps), np.int64)

    def check(self, header: MapHeader) -> None:
        """Raise :class:`MapFileError` where the arrays do not fit each other or the header."""
        for field in fields(MapArrays):
            kind = getattr(self, field.name).dtype.kind
            if kind not in ARRAY_KINDS[field.name]:
                raise MapFileError(f"{field.name} has dtype {getattr(self, field.name).dtype}")
        k, lm = header.keyframes, header.landmarks
        shapes = {"keyframe_poses": (k, 4, 4), "keyframe_stamps": (k,), "keyframe_culled": (k,),
                  "keyframe_camera": (k,),
                  "keyframe_first": (k + 1,), "landmark_positions": (lm, 3),
                  "landmark_descriptors": (lm, header.descriptor_dim), "landmark_accepted": (lm,),
                  "landmark_rejected": (lm,), "landmark_bad": (lm,)}
        for name, shape in shapes.items():
            if getattr(self, name).shape != shape:
                raise MapFileError(f"{name} has shape {getattr(self, name).shape}, the header says {shape}")
        points = len(self.keypoint_landmark)
        if self.keypoint_xy.shape != (points, 2) or self.keypoint_depth.shape != (points,):
            raise MapFileError(f"keypoint arrays disagree: xy {self.keypoint_xy.shape}, depth "
                               f"{self.keypoint_depth.shape}, landmark {self.keypoint_landmark.shape}")
        first = self.keyframe_first
        if len(first) and (first[0] != 0 or first[-1] != points or np.any(np.diff(first) < 0)):
            raise MapFileError("keyframe_first does not split the keypoints in order")
        if str(self.landmark_descriptors.dtype) != header.descriptor_dtype:
            raise MapFileError(f"descriptors are {self.landmark_descriptors.dtype}, the header says "
                               f"{header.descriptor_dtype}")
        if np.any((self.keyframe_camera < 0) | (self.keyframe_camera > len(header.cameras))):
            raise MapFileError(f"a keyframe names a camera the header does not have ({len(header.cameras) + 1})")
        if np.any((self.keypoint_landmark < -1) | (self.keypoint_landmark >= lm)):
            raise MapFileError("a keypoint observes a landmark the map does not have")
        for name in ("keyframe_poses", "keyframe_stamps", "landmark_positions", "keypoint_xy", "keypoint_depth"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise MapFileError(f"{name} holds values that are not finite")
        if k and not np.allclose(self.keyframe_poses[:, 3], [0, 0, 0, 1]):
            raise MapFileError("a keyframe pose is not a rigid transform")


#: the dtype kinds each array may have (f float, i/u integer, b bool)
ARRAY_KINDS = {"keyframe_poses": "f", "keyframe_stamps": "f", "keyframe_culled": "b", "keyframe_first": "iu",
               "keypoint_xy": "f", "keypoint_depth": "f", "keypoint_landmark": "i", "landmark_positions": "f",
               "landmark_descriptors": "fu", "landmark_accepted": "iu", "landmark_rejected": "iu", "landmark_bad": "b",
               "keyframe_camera": "iu"}


@dataclass
class MapFile:
    """A map as stored: its header and its arrays."""

    header: MapHeader
    arrays: MapArrays


def arrays_file(arrays: MapArrays, camera: CameraIntrinsics, config: PipelineConfig, name: str, built_by: str = "",
                parent: MapHeader | None = None, cameras: list[CameraIntrinsics] | None = None,
                camera_robots: list[str] | None = None) -> MapFile:
    """A map's arrays (a tracker's map, a copy taken earlier, a shared map's) as a map file named ``name``;
    ``cameras`` and ``camera_robots``: see :class:`MapHeader`."""
    try:
        sha256 = get_spec(descriptor_space(config.detector.model)).sha256
    except ModelError:
        sha256 = ""
    header = MapHeader(name=name, built_by=built_by,
                       parent=None if parent is None else f"{parent.name}@{parent.created:.3f}",
                       camera=camera, detector_model=config.detector.model, detector_sha256=sha256,
                       detector_config=config.detector.model_dump(mode="json"),
                       descriptor_dim=arrays.landmark_descriptors.shape[1],
                       descriptor_dtype=str(arrays.landmark_descriptors.dtype),
                       keyframes=len(arrays.keyframe_stamps), landmarks=len(arrays.landmark_positions),
                       cameras=cameras or [], camera_robots=camera_robots or [])
    return MapFile(header, arrays)


def encode_map(map_file: MapFile) -> bytes:
    """A map file's bytes (what :func:`write_map` writes, and what goes over the bus)."""
    map_file.arrays.check(map_file.header)
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_STORED) as archive:
        # written in this twohr's format, whatever the version it was read in (a version-1 map gets its owners)
        archive.writestr("header.json", map_file.header.model_copy(update={"version": VERSION}).model_dump_json(
            indent=1))
        for field in fields(MapArrays):
            array = io.BytesIO()
            np.save(array, np.ascontiguousarray(getattr(map_file.arrays, field.name)), allow_pickle=False)
            archive.writestr(f"{field.name}.npy", array.getvalue())
    return buffer.getvalue()


def write_map(path: str | Path, map_file: MapFile) -> int:
    """Write ``map_file`` to ``path`` atomically; returns its size in bytes."""
    data = encode_map(map_file)
    # private (0600, its folder 0700): a map is the robots' surroundings
    write_atomic(path, data, durable=True, folder_mode=0o700)
    return len(data)


def read_header(path: str | Path) -> MapHeader:
    """The header of a map file alone (cheap: for listings); :class:`MapFileError` when it cannot be read."""
    with _archive(path) as archive:
        return _header(archive, path)


def read_map(source: str | Path | bytes, detector: DetectorConfig | None = None) -> MapFile:
    """A map file (a path, or its bytes), checked through; with ``detector``, also that it was built with that
    detector (:meth:`MapHeader.check_built_with`)."""
    path = "map" if isinstance(source, bytes) else source
    with _archive(source) as archive:
        header = _header(archive, path)
        if detector is not None:
            header.check_built_with(detector, str(path))
        members = {info.filename: info for info in archive.infolist()}
        values = {}
        for field in fields(MapArrays):
            member = members.get(f"{field.name}.npy")
            if member is None and field.name == "keyframe_camera" and header.version < 3:
                continue  # every keyframe taken with the header's camera
            if member is None:
                raise MapFileError(f"{path}: {field.name}.npy is missing")
            if member.compress_type != zipfile.ZIP_STORED:  # stored as written: no member can expand in memory
                raise MapFileError(f"{path}: {member.filename} is compressed; map files store their arrays as they are")
            try:
                values[field.name] = np.load(io.BytesIO(archive.read(member)), allow_pickle=False)
            except Exception as exc:  # a corrupt member: whatever numpy or zipfile raise, one line
                raise MapFileError(f"{path}: {member.filename} cannot be read ({type(exc).__name__})") from None
    arrays = MapArrays(**values)
    try:
        arrays.check(header)
    except MapFileError as exc:
        raise MapFileError(f"{path}: {exc}") from None
    except Exception as exc:  # an array of a shape nothing here expects (0-d, structured)
        raise MapFileError(f"{path}: its arrays do not fit a map ({type(exc).__name__})") from None
    return MapFile(header, arrays)


def verify_bytes(data: bytes) -> MapHeader:
    """Check a map file's bytes (say, an upload) through; returns its header."""
    return read_map(data).header


def with_owners(data: bytes, owners: list[str], contributors: list[str] | None = None) -> bytes:
    """A map file's bytes with ``owners`` and ``contributors`` in its header (and this twohr's format version); the
    arrays are copied as they are."""
    with _archive(data) as archive:
        header = _header(archive, "map")
        header = MapHeader.model_validate({**header.model_dump(), "owners": owners,
                                           "contributors": contributors or [], "version": VERSION})
        buffer = io.BytesIO()
        with zipfile.ZipFile(buffer, "w", zipfile.ZIP_STORED) as out:
            out.writestr("header.json", header.model_dump_json(indent=1))
            for member in archive.infolist():
                if member.filename != "header.json":
                    out.writestr(member.filename, archive.read(member))
    return buffer.getvalue()


class _archive:
    """The map file (a path or its bytes) as an open zip archive; :class:`MapFileError` when it is missing or not a
    zip."""

    def __init__(self, source: str | Path | bytes) -> None:
        self.source = source

    def __enter__(self) -> zipfile.ZipFile:
        source = self.source
        if not isinstance(source, bytes) and not Path(source).is_file():
            raise MapFileError(f"{source}: no such map file")
        try:
            self.zip = zipfile.ZipFile(io.BytesIO(source) if isinstance(source, bytes) else Path(source))
        except (zipfile.BadZipFile, OSError) as exc:
            raise MapFileError(f"{'map' if isinstance(source, bytes) else source}: not a twohr map file "
                               f"({exc})") from None
        return self.zip

    def __exit__(self, *exc) -> None:
        self.zip.close()


def _header(archive: zipfile.ZipFile, path) -> MapHeader:
    try:
        raw = json.loads(archive.read("header.json"))
    except KeyError:
        raise MapFileError(f"{path}: not a twohr map file (no header.json)") from None
    except Exception as exc:  # a corrupt member: whatever zipfile or json raise, one line
        raise MapFileError(f"{path}: header.json cannot be read ({type(exc).__name__})") from None
    if not isinstance(raw, dict) or raw.get("format") != FORMAT:
        found = raw.get("format") if isinstance(raw, dict) else raw
        raise MapFileError(f"{path}: not a twohr map file (format {found!r})")
    if raw.get("version") not in READS:
        raise MapFileError(f"{path}: map format version {raw.get('version')}, this twohr reads versions "
                           f"{', '.join(map(str, READS))}")
    if raw["version"] == 1:  # before maps had owners: the operator's
        if "owners" in raw:
            raise MapFileError(f"{path}: header.json: a version-1 map has no owners")
        raw = {**raw, "owners": [OPERATOR]}
    try:
        return MapHeader.model_validate(raw)
    except ValidationError as exc:
        raise MapFileError(f"{path}: header.json: {validation_problems(exc)}") from None
