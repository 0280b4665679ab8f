"""The map store: a folder of maps, numbered versions of each, and who may change them.

:class:`MapStore` keeps a folder of map files (:mod:`twohr.mapfile`): numbered versions of each map (at most
``keep``), the latest under the map's name, with rollback; every change holds one lock that other processes on the
folder respect too, and what is audited of a change (``on_saved``) is written under it, so the trail lists the
versions in the order they were made. A map is changed by its owners (who built it first, in its header), by the
operator (:data:`~twohr.mapfile.OPERATOR`), and by the robots the operator granted it (:class:`MapGrants`,
``twohr keys grant``): :func:`may_change`. :func:`without_robot` takes one robot's keyframes out of a shared map.

The map room (``twohr_services.mapserver``) serves the store on the bus, the gateway over HTTP (``/maps``), and
``twohr maps`` on the folder itself.
"""

from __future__ import annotations

import contextlib
import datetime
import fcntl
import os
import re
import threading
import time
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from .files import write_atomic
from .mapfile import (
    NAME_PATTERN,
    OPERATOR,
    SUFFIX,
    MapArrays,
    MapFile,
    MapFileError,
    MapHeader,
    check_owner,
    read_header,
    verify_bytes,
    with_owners,
)

#: how many versions of each map a store keeps unless told otherwise, and at most
DEFAULT_KEEP, MAX_KEEP = 10, 10_000
#: the operator's map grants (:class:`MapGrants`), in the key folders of the gateway and of the map room
GRANTS_FILE = "grants.json"


class MapMissingError(MapFileError):
    """No map, or no kept version, by the name or number asked for."""


class MapAccessError(MapFileError):
    """An identity that may not replace a map: neither one of its owners nor granted it by the operator."""


def check_map_name(name: str) -> str:
    """``name`` if a map may have it (:data:`~twohr.mapfile.NAME_PATTERN`, not ending in ``.v<number>``, a kept
    version's name); :class:`MapFileError` (one line) otherwise."""
    if not re.fullmatch(NAME_PATTERN, name) or _is_version(name):
        raise MapFileError(f"{name!r} is not a map name ({NAME_PATTERN}, not ending in .v<number>)")
    return name


class MapGrants(BaseModel):
    """The operator's grants (``grants.json``, written by ``twohr keys grant`` in the key folders of the gateway and
    of the map room): the robots that may build or extend a map they do not own, by map name, with when each was
    granted."""

    model_config = ConfigDict(extra="forbid")

    maps: dict[str, dict[str, datetime.datetime]] = Field(default_factory=dict)

    def allows(self, robot: str, name: str) -> bool:
        """Whether ``robot`` holds the operator's grant on map ``name``."""
        return robot in self.maps.get(name, {})

    @classmethod
    def load(cls, path: Path | None) -> MapGrants:
        """The grants in file ``path``: none where there is no such file (or no path); :class:`MapFileError` (one
        line) for a file that holds no grants."""
        if path is None:
            return cls()
        try:
            return cls.model_validate_json(Path(path).read_bytes())
        except FileNotFoundError:
            return cls()
        except (OSError, ValueError) as exc:
            raise MapFileError(f"{path}: not the operator's map grants ({str(exc).splitlines()[0]})") from None


def may_change(who: str, name: str, owners: list[str], grants: MapGrants) -> bool:
    """Whether identity ``who`` may build or extend map ``name`` owned by ``owners``: the operator, an owner, or a
    robot the operator granted it. A map's contributors have no right of their own: a robot that changed it under a
    grant needs the grant again."""
    return who == OPERATOR or who in owners or grants.allows(who, name)


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


#: what a change of the store calls under its lock with the version it made (:meth:`MapStore.save`)
OnSaved = Callable[[MapEntry], None]


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

    def read(self, name: str) -> bytes:
        """The latest version's bytes of map ``name`` (:class:`MapMissingError` when there is none)."""
        try:
            return self.latest_file(name).read_bytes()
        except FileNotFoundError:  # removed between the look and the read
            raise MapMissingError(f"no map named {name!r}") from None

    def save(self, data: bytes, name: str | None = None, *, builder: str,
             may_replace: Callable[[list[str]], bool] | None = None, on_saved: OnSaved | None = None) -> MapEntry:
        """Keep a map file's bytes (checked through first) as the next version of ``name`` (default, and it must
        be: the name in its header, the frame its poses are in), built by ``builder`` (a robot id, or
        :data:`OPERATOR`). A new map is ``builder``'s: its one owner. An existing map keeps its owners; a
        ``builder`` not among them (a robot under the operator's grant, the operator) is recorded among its
        ``contributors``, which gives no right: the grant stays what lets a robot change a map it does not own.
        ``may_replace(owners)``, asked under the store's lock when the map exists, False: :class:`MapAccessError`
        and nothing changes. The latest file is replaced atomically: a reader always finds the old or the new one.
        ``on_saved(entry)`` is called under the lock once the version is the latest (its audit: see the module)."""
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
            return self._add_version(name, path, with_owners(data, owners, contributors), on_saved)

    def rollback(self, name: str, version: int, on_saved: OnSaved | None = None) -> MapEntry:
        """Make kept version ``version`` of map ``name`` the latest again, byte for byte, as a new version (the
        versions after it stay, until the store's limit prunes them); :class:`MapMissingError` when the map or that
        version is not kept, :class:`MapFileError` when it is already the latest or no longer readable;
        ``on_saved`` as for :meth:`save`."""
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
            return self._add_version(name, path, data, on_saved)

    def _add_version(self, name: str, path: Path, data: bytes, on_saved: OnSaved | None) -> MapEntry:
        """Write ``data`` as the next version of map ``name`` and make it the latest (the store's lock held): the
        numbered file whole first (a temporary name, renamed), then the readers' link to it."""
        numbered = self._numbered(name)
        latest = self._latest(name, numbered)
        if latest is not None and latest not in numbered:  # the earlier layout: the latest gets its number first
            os.link(path, self.root / f"{name}.v{latest}{SUFFIX}")
        number = (latest or 0) + 1
        numbered_path = self.root / f"{name}.v{number}{SUFFIX}"
        write_atomic(numbered_path, data, durable=True, folder_mode=0o700)  # private: the robots' surroundings
        _link_atomically(numbered_path, path)
        for old in sorted({*self._numbered(name)})[:-self.keep]:
            (self.root / f"{name}.v{old}{SUFFIX}").unlink(missing_ok=True)
        entry = self.entry(name)
        if on_saved is not None:
            on_saved(entry)
        return entry

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

