"""The map file: one self-describing file per map, that a robot can come back to and another robot can load.

A map file is a zip archive (``.map``) of ``header.json`` (:class:`MapHeader`: format and version, the map's name
and frame, the camera, the detector model and config it was built with, counts, provenance) and one ``.npy`` array
per field of :class:`MapArrays`, read with ``allow_pickle=False``. Keyframes keep their pose, stamp and keypoints
(pixels, depth, the landmark each one observes); a keypoint that observes a landmark has that landmark's
descriptor, the only descriptors a map keeps (those of unmatched keypoints are dropped, as in memory).

Written atomically (a temporary file beside the target, fsync, rename). :func:`read_map` checks everything and
answers a wrong, corrupt or inconsistent file, or one built with another detector model, with one
:class:`MapFileError` line. Plain arrays and pydantic only: the tracker, the gateway and the CLI all use it.

Format version 2 adds the map's owners (:attr:`MapHeader.owners`: who built it first) and contributors (who changed
it under a grant: a record, no right); a version-1 file still loads, owned by the operator. :class:`MapStore` keeps
a folder of maps, numbered versions of each (at most ``keep``), with rollback; :class:`MapGrants` lists the robots
the operator lets build or extend a map they do not own.
"""

from __future__ import annotations

import contextlib
import datetime
import fcntl
import io
import json
import os
import re
import tempfile
import threading
import time
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from .config import DetectorConfig, PipelineConfig
from .dataset import CameraIntrinsics
from .errors import ModelError, TwohrError, validation_problems
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
#: how many versions of each map a store keeps unless told otherwise
DEFAULT_KEEP = 10
#: the operator's map grants (:class:`MapGrants`), in the gateway's key folder
GRANTS_FILE = "grants.json"


class MapFileError(TwohrError):
    """A map file that cannot be used: missing, corrupt, of another format or version, inconsistent, or built with
    another detector model than the one asked for."""


class MapMissingError(MapFileError):
    """No map, or no kept version, by the name or number asked for."""


class MapAccessError(MapFileError):
    """An identity that may not replace a map: neither one of its owners nor granted it by the operator."""


def check_map_name(name: str) -> str:
    """``name`` if a map may have it (:data:`NAME_PATTERN`, not ending in ``.v<number>``, a kept version's name);
    :class:`MapFileError` (one line) otherwise."""
    if not re.fullmatch(NAME_PATTERN, name) or _is_version(name):
        raise MapFileError(f"{name!r} is not a map name ({NAME_PATTERN}, not ending in .v<number>)")
    return name


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


def write_bytes_atomically(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that a reader finds the old file or the whole new one, never a part (temporary
    file beside it, fsync, rename, fsync of the folder). The file is private (0600: a map is the robots' surroundings),
    and a folder made for it too (0700)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(handle, "wb") as out:
            out.write(data)
            out.flush()
            os.fsync(out.fileno())
        os.replace(temporary, path)  # mkstemp made it 0600
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    directory = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(directory)  # the rename itself survives a power cut
    finally:
        os.close(directory)


def write_map(path: str | Path, map_file: MapFile) -> int:
    """Write ``map_file`` to ``path`` atomically; returns its size in bytes."""
    data = encode_map(map_file)
    write_bytes_atomically(path, data)
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


class MapGrants(BaseModel):
    """The operator's grants (``grants.json`` in the gateway's key folder, written by ``twohr keys grant``): the
    robots that may build or extend a map they do not own, by map name, with when each was granted."""

    model_config = ConfigDict(extra="forbid")

    maps: dict[str, dict[str, datetime.datetime]] = Field(default_factory=dict)

    def allows(self, robot: str, name: str) -> bool:
        """Whether ``robot`` holds the operator's grant on map ``name``."""
        return robot in self.maps.get(name, {})


class MapEntry(BaseModel):
    """One map of a :class:`MapStore`, as ``GET /maps`` and ``twohr maps list`` show it."""

    name: str
    version: int = Field(description="the latest version's number: 1 for the first map saved under this name, then "
                         "one more per save or rollback (numbers are never reused)")
    versions: list[int] = Field(default_factory=list, description="the versions the store keeps, oldest first (the "
                                "oldest go past the store's limit; the others keep their numbers)")
    owners: list[str] = Field(default_factory=list, description="the identities that own the latest version: "
                              "who built the map first (a robot, or the operator)")
    contributors: list[str] = Field(default_factory=list, description="those that changed it under the operator's "
                                    "grant (or as the operator) without owning it: a record, no right")
    keyframes: int
    landmarks: int
    size_bytes: int
    built_by: str
    created: float
    detector_model: str


class MapStore:
    """A folder of maps. Every version of map ``name`` is ``<name>.v<N>.map`` (N = 1, 2, … never reused), written
    whole under a temporary name and renamed to its number, so that a numbered file is always complete; the highest
    numbered is the latest. ``<name>.map`` is a hard link to it, the one readers outside the store load; a file is
    never overwritten in place. At most ``keep`` versions are kept: past it the oldest go. A save interrupted
    between its numbered file and the link leaves ``<name>.map`` on the version before: the store still serves the
    highest numbered, and the next change links it. A folder written before versions were numbered this way
    (``<name>.map`` none of the numbered files) is read as it is, its latest one more than its highest numbered, and
    converted at its next save. Changes hold a lock that other processes on the folder (``twohr maps rollback``)
    respect too."""

    def __init__(self, root: str | Path, keep: int = DEFAULT_KEEP) -> None:
        if keep < 1:
            raise MapFileError(f"a map store keeps at least one version of each map, not {keep}")
        self.root = Path(root)
        self.keep = keep

    def path(self, name: str) -> Path:
        """The readers' file of map ``name``, ``<name>.map`` (:class:`MapFileError` for a name that is not one)."""
        return self.root / f"{check_map_name(name)}{SUFFIX}"

    def names(self) -> list[str]:
        """The names of the maps in the folder (with a readers' file or a numbered version)."""
        stems = {p.name.removesuffix(SUFFIX) for p in self.root.glob(f"*{SUFFIX}")}
        names = {stem.rpartition(".v")[0] if _is_version(stem) else stem for stem in stems}
        return sorted(name for name in names if re.fullmatch(NAME_PATTERN, name) and not _is_version(name))

    def _numbered(self, name: str) -> dict[int, Path]:
        """Every numbered version file of map ``name``, by number."""
        found = {}
        for p in self.root.glob(f"{name}.v*{SUFFIX}"):  # a map name has no glob characters
            number = p.name[len(name) + 2:-len(SUFFIX)]
            if number.isdigit() and p.name == f"{name}.v{int(number)}{SUFFIX}":
                found[int(number)] = p
        return found

    def _latest(self, name: str, numbered: dict[int, Path]) -> int | None:
        """The latest version's number (None: no map ``name``): the highest numbered file, unless ``<name>.map`` is
        none of the numbered files (a store of the earlier layout, whose latest had no number): then one more."""
        path = self.path(name)
        if not numbered:
            return 1 if path.is_file() else None
        top = max(numbered)
        if not path.is_file() or any(_same_file(path, other) for other in numbered.values()):
            return top
        return top + 1

    def latest_file(self, name: str) -> Path:
        """The latest version's file of map ``name`` (:class:`MapMissingError` when there is none): its numbered file,
        or ``<name>.map`` in a store of the earlier layout."""
        numbered = self._numbered(name)
        latest = self._latest(name, numbered)
        if latest is None:
            raise MapMissingError(f"no map named {name!r}")
        return numbered.get(latest, self.path(name))

    def numbers(self, name: str) -> list[int]:
        """The numbers of the kept versions of map ``name``, oldest first, the latest last ([] for no map)."""
        numbered = self._numbered(name)
        latest = self._latest(name, numbered)
        return sorted({*numbered, latest}) if latest is not None else []

    def versions(self, name: str) -> list[Path]:
        """The kept earlier versions of map ``name`` (the latest left out), oldest first."""
        numbered = self._numbered(name)
        latest = self._latest(name, numbered)
        return [p for number, p in sorted(numbered.items()) if number != latest]

    def version_path(self, name: str, version: int) -> Path:
        """The file of version ``version`` of map ``name``; :class:`MapMissingError` when it is not kept."""
        numbered = self._numbered(name)
        latest = self._latest(name, numbered)
        if version == latest:
            return numbered.get(version, self.path(name))
        if version not in numbered:
            kept = sorted({*numbered, *([latest] if latest else [])})
            raise MapMissingError(f"map {name!r} has no version {version}" + (
                f" (kept: {', '.join(map(str, kept))})" if kept else ""))
        return numbered[version]

    def header(self, name: str) -> MapHeader | None:
        """The header of map ``name``'s latest version; None when there is no such map. An unreadable file's is
        the operator's alone (owners ``[@operator]``, no contributors) as far as rights go: :meth:`owners`."""
        try:
            path = self.latest_file(name)
        except MapMissingError:
            return None
        return read_header(path)

    def owners(self, name: str) -> list[str] | None:
        """The owners of map ``name``'s latest version; None when there is no such map. An unreadable file is the
        operator's alone."""
        try:
            header = self.header(name)
        except MapFileError:
            return [OPERATOR]
        return None if header is None else header.owners

    def entry(self, name: str) -> MapEntry:
        """What the latest version of map ``name`` is; :class:`MapFileError` when it is missing or unreadable."""
        path = self.latest_file(name)
        header = read_header(path)
        numbers = self.numbers(name)
        return MapEntry(name=name, version=numbers[-1], versions=numbers, owners=header.owners,
                        contributors=header.contributors, keyframes=header.keyframes, landmarks=header.landmarks,
                        size_bytes=path.stat().st_size, built_by=header.built_by, created=header.created,
                        detector_model=header.detector_model)

    def entries(self) -> tuple[list[MapEntry], dict[str, str]]:
        """Every readable map, and why each unreadable one is not (by name)."""
        good, bad = [], {}
        for name in self.names():
            try:
                good.append(self.entry(name))
            except MapFileError as exc:
                bad[name] = str(exc)
        return good, bad

    def save(self, data: bytes, name: str | None = None, *, builder: str,
             may_replace: Callable[[list[str]], bool] | None = None) -> MapEntry:
        """Keep a map file's bytes (checked through first) as the next version of ``name`` (default, and it must
        be: the name in its header, the frame its poses are in), built by ``builder`` (a robot id, or
        :data:`OPERATOR`). A new map is ``builder``'s: its one owner. An existing map keeps its owners; a
        ``builder`` not among them (a robot under the operator's grant, the operator) is recorded among its
        ``contributors``, which gives no right: the grant stays what lets a robot change a map it does not own.
        ``may_replace(owners)``, asked under the store's lock when the map exists, False: :class:`MapAccessError`
        and nothing changes. The latest file is replaced atomically: a reader always finds the old or the new one."""
        header = verify_bytes(data)
        name = name or header.name
        if name != header.name:
            raise MapFileError(f"the file holds map {header.name!r}, not {name!r} (a map's name is its frame)")
        check_owner(builder)
        path = self.path(name)
        with self._locked():  # an upload and a tracker's save may come at once, from two processes too
            try:
                current = self.header(name)
            except MapFileError:  # an unreadable latest version: the operator's alone
                current = MapHeader.model_construct(owners=[OPERATOR], contributors=[])
            if current is not None and may_replace is not None and not may_replace(current.owners):
                owners = current.owners
                raise MapAccessError(f"map {name!r} is owned by {', '.join(owners)}: building or extending it needs "
                                     f"ownership or the operator's grant (twohr keys grant DIR ROBOT --map {name})")
            if current is None:
                owners, contributors = [builder], []
            elif builder in current.owners:
                owners, contributors = current.owners, current.contributors
            else:
                owners, contributors = current.owners, [*current.contributors, builder]
            return self._add_version(name, path, with_owners(data, owners, contributors))

    def rollback(self, name: str, version: int) -> MapEntry:
        """Make kept version ``version`` of map ``name`` the latest again, byte for byte, as a new version (the
        versions after it stay, until the store's limit prunes them); :class:`MapMissingError` when the map or that
        version is not kept, :class:`MapFileError` when it is already the latest or no longer readable."""
        path = self.path(name)
        with self._locked():
            numbered = self._numbered(name)
            latest = self._latest(name, numbered)
            if latest is None:
                raise MapMissingError(f"no map named {name!r}")
            if version == latest:
                raise MapFileError(f"version {version} is already the latest of map {name!r}")
            data = self.version_path(name, version).read_bytes()
            verify_bytes(data)  # a damaged file is not made the latest
            return self._add_version(name, path, data)

    def _add_version(self, name: str, path: Path, data: bytes) -> MapEntry:
        """Write ``data`` as the next version of map ``name`` and make it the latest (the store's lock held): the
        numbered file whole first (a temporary name, renamed), then the readers' link to it."""
        numbered = self._numbered(name)
        latest = self._latest(name, numbered)
        if latest is not None and latest not in numbered:  # the earlier layout: the latest gets its number first
            os.link(path, self.root / f"{name}.v{latest}{SUFFIX}")
        number = (latest or 0) + 1
        numbered_path = self.root / f"{name}.v{number}{SUFFIX}"
        write_bytes_atomically(numbered_path, data)
        _link_atomically(numbered_path, path)
        for old in sorted({*self._numbered(name)})[:-self.keep]:
            (self.root / f"{name}.v{old}{SUFFIX}").unlink(missing_ok=True)
        return self.entry(name)

    def delete(self, name: str) -> bool:
        """Remove map ``name`` and its kept versions; False when there was none."""
        path = self.path(name)
        with self._locked():
            numbered = self._numbered(name)
            if not path.exists() and not numbered:
                return False
            path.unlink(missing_ok=True)  # readers lose it first
            for old in numbered.values():
                old.unlink(missing_ok=True)
            return True

    @contextlib.contextmanager
    def _locked(self) -> Iterator[None]:
        """The store's lock: this process's threads, and (a lock file in the folder) other processes."""
        self.root.mkdir(parents=True, exist_ok=True, mode=0o700)
        with _STORE_LOCK:
            handle = os.open(self.root / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o600)
            try:
                fcntl.flock(handle, fcntl.LOCK_EX)
                yield
            finally:
                os.close(handle)  # releases the lock


_STORE_LOCK = threading.Lock()
LOCK_FILE = ".store.lock"


def _same_file(a: Path, b: Path) -> bool:
    """Whether two paths hold the same version: the same file (a hard link, by inode), or, in a store copied without
    its links, the same size and the same members (names, sizes and CRC-32s in the zip's directory: no data is
    read)."""
    try:
        first, second = a.stat(), b.stat()
    except FileNotFoundError:
        return False
    if (first.st_dev, first.st_ino) == (second.st_dev, second.st_ino):
        return True
    if first.st_size != second.st_size:
        return False
    try:
        return _members(a) == _members(b)
    except (OSError, zipfile.BadZipFile):
        return False


def _members(path: Path) -> list[tuple[str, int, int]]:
    """A zip file's members as its directory lists them: name, CRC-32 and size of each."""
    with zipfile.ZipFile(path) as archive:
        return [(info.filename, info.CRC, info.file_size) for info in archive.infolist()]


def _link_atomically(source: Path, target: Path) -> None:
    """Make ``target`` a hard link to ``source``, replacing whatever ``target`` was at once."""
    temporary = target.with_name(f".{target.name}.{os.getpid()}.{threading.get_ident()}.link")
    temporary.unlink(missing_ok=True)
    os.link(source, temporary)
    try:
        os.replace(temporary, target)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    directory = os.open(target.parent, os.O_RDONLY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)


def _is_version(stem: str) -> bool:
    """True for a kept earlier version's file stem, ``<name>.v<N>``."""
    head, _, tail = stem.rpartition(".v")
    return bool(head) and tail.isdigit()


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


def without_robot(map_file: MapFile, robot: str) -> MapFile:
    """A shared map without robot ``robot``'s keyframes (a revoked robot's, say): the keyframes its cameras took
    (``camera_robots``) go, and the landmarks only they observed; :class:`MapFileError` where the map has no
    keyframe of that robot, or nothing would be left."""
    header, arrays = map_file.header, map_file.arrays
    robots = header.camera_robots or [""] * (1 + len(header.cameras))
    gone_cameras = [i for i, name in enumerate(robots) if name == robot]
    keep = ~np.isin(arrays.keyframe_camera, gone_cameras)
    if keep.all():
        raise MapFileError(f"map {header.name} holds no keyframe of robot {robot!r} (its robots: "
                           f"{', '.join(sorted(set(r for r in robots if r))) or 'not recorded'})")
    if not keep.any():
        raise MapFileError(f"map {header.name} holds robot {robot!r}'s keyframes alone: nothing would be left")
    first = arrays.keyframe_first
    parts = [np.arange(first[k], first[k + 1]) for k in np.flatnonzero(keep)]
    rows = np.concatenate(parts) if parts else np.zeros(0, np.int64)
    observed = arrays.keypoint_landmark[rows]
    landmarks = np.unique(observed[observed >= 0])
    renumber = np.full(len(arrays.landmark_positions), -1, np.int64)
    renumber[landmarks] = np.arange(len(landmarks))
    cameras = [c for i, c in enumerate([header.camera, *header.cameras]) if i not in gone_cameras]
    camera_index = np.cumsum([i not in gone_cameras for i in range(len(robots))]) - 1
    kept = MapArrays(
        keyframe_poses=arrays.keyframe_poses[keep], keyframe_stamps=arrays.keyframe_stamps[keep],
        keyframe_culled=arrays.keyframe_culled[keep],
        keyframe_first=np.concatenate([[0], np.cumsum([len(p) for p in parts])]).astype(np.int64),
        keypoint_xy=arrays.keypoint_xy[rows], keypoint_depth=arrays.keypoint_depth[rows],
        keypoint_landmark=np.where(observed >= 0, renumber[np.maximum(observed, 0)], -1),
        landmark_positions=arrays.landmark_positions[landmarks],
        landmark_descriptors=arrays.landmark_descriptors[landmarks],
        landmark_accepted=arrays.landmark_accepted[landmarks], landmark_rejected=arrays.landmark_rejected[landmarks],
        landmark_bad=arrays.landmark_bad[landmarks], keyframe_camera=camera_index[arrays.keyframe_camera[keep]])
    kept_header = header.model_copy(update={
        "camera": cameras[0], "cameras": cameras[1:],
        "camera_robots": [r for i, r in enumerate(robots) if i not in gone_cameras] if header.camera_robots else [],
        "keyframes": int(keep.sum()), "landmarks": len(landmarks),
        "built_by": f"{header.built_by}; robot {robot}'s keyframes removed", "created": time.time()})
    return MapFile(kept_header, kept)


def write_ply(path: str | Path, points: np.ndarray, sources: np.ndarray | None = None) -> int:
    """Points (N, 3) as a binary little-endian PLY point cloud (``sources``: an integer per point, written as
    property ``source``: which robot's keyframes made it), written atomically; returns its size in bytes."""
    points = np.asarray(points, np.float32).reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")] + ([("source", "<i4")] if sources is not None else [])
    rows = np.zeros(len(points), dtype=fields)
    rows["x"], rows["y"], rows["z"] = points.T
    if sources is not None:
        rows["source"] = sources
    header = ["ply", "format binary_little_endian 1.0", "comment twohr map landmarks (world frame, metres)",
              f"element vertex {len(points)}", "property float x", "property float y", "property float z"]
    header += ["property int source"] if sources is not None else []
    data = ("\n".join(header + ["end_header"]) + "\n").encode() + rows.tobytes()
    write_bytes_atomically(path, data)
    return len(data)
