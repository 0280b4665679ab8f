"""``twohr maps``: the maps in a map store folder (``twohr up --maps DIR``) or in files: list, show, verify, export
the landmarks as a point cloud, roll a map back to an earlier version or take one robot's keyframes out of a shared
map (both on the folder, when no stack serves it; a running stack's operator rolls back with
``POST /maps/NAME/rollback?version=N``)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

#: the most versions of each map a store may be told to keep (``twohr.mapstore.MAX_KEEP``, read without importing
#: the store library into every command's start)
MAX_MAP_VERSIONS = 10_000


def parse_map_versions(value: str | int) -> int:
    """``--map-versions`` (``twohr up``, ``twohr maps rollback``): a whole number of versions of each map to keep,
    1 to :data:`MAX_MAP_VERSIONS`; :class:`~twohr.errors.ConfigError` in one line for anything else."""
    from twohr.errors import ConfigError

    text = str(value).strip()
    if not (text.isascii() and text.isdigit()) or not 1 <= int(text) <= MAX_MAP_VERSIONS:
        raise ConfigError(f"--map-versions {value}: keep at least one version of each map and at most "
                          f"{MAX_MAP_VERSIONS} (a whole number)")
    return int(text)


def _list(args: argparse.Namespace) -> int:
    from twohr.errors import TwohrError
    from twohr.mapstore import MapStore

    if not Path(args.maps).is_dir():
        raise TwohrError(f"no map store folder {args.maps} (twohr up --maps DIR makes one)")
    good, bad = MapStore(args.maps).entries()
    print(f"{'name':24} {'version':>7} {'kept':>8} {'keyframes':>9} {'landmarks':>9} {'size':>10}  built")
    for entry in good:
        built = time.strftime("%Y-%m-%d %H:%M", time.localtime(entry.created))
        kept = f"{entry.versions[0]}-{entry.versions[-1]}" if len(entry.versions) > 1 else str(entry.version)
        print(f"{entry.name:24} {entry.version:>7} {kept:>8} {entry.keyframes:>9} {entry.landmarks:>9} "
              f"{entry.size_bytes / 1e6:>8.2f} MB  {built} by {entry.built_by or '?'}; owners "
              f"{', '.join(entry.owners)}")
    for name, why in bad.items():
        print(f"{name:24} UNREADABLE: {why}")
    return 0 if not bad else 1


def _target(args: argparse.Namespace, item: str) -> Path:
    """A map file named by path, or by name in the ``--maps`` store."""
    from twohr.mapstore import MapStore

    path = Path(item)
    return path if path.suffix == ".map" or path.is_file() else MapStore(args.maps).path(item)


def _show(args: argparse.Namespace) -> int:
    from twohr.mapfile import read_map

    path = _target(args, args.map)
    header = read_map(path).header
    size = path.stat().st_size
    print(json.dumps({**header.model_dump(mode="json"), "file": str(path), "size_bytes": size,
                      "bytes_per_keyframe": round(size / max(1, header.keyframes))}, indent=1))
    return 0


def _verify(args: argparse.Namespace) -> int:
    from twohr.config import DetectorConfig
    from twohr.mapfile import MapFileError, read_map

    detector = None if args.detector_model is None else DetectorConfig(model=args.detector_model)
    failed = 0
    for item in args.maps_or_files:
        try:
            path = _target(args, item)
            header = read_map(path, detector=detector).header
        except MapFileError as exc:
            failed += 1
            print(f"FAIL {exc}")
            continue
        print(f"ok   {path}: map {header.name}, {header.keyframes} keyframes, {header.landmarks} landmarks, "
              f"detector {header.detector_model}")
    return 2 if failed else 0


def _rollback(args: argparse.Namespace) -> int:
    from twohr.audit import AuditLog
    from twohr.errors import TwohrError
    from twohr.mapfile import OPERATOR
    from twohr.mapstore import MapStore

    from ..supervisor import audit_file

    keep = parse_map_versions(args.map_versions)
    if not Path(args.maps).is_dir():
        raise TwohrError(f"no map store folder {args.maps}")
    audit = Path(args.audit) if args.audit else audit_file(args.maps)
    entry = MapStore(args.maps, keep).rollback(args.map, args.version, on_saved=lambda made: AuditLog(audit).record(
        "map.rollback", OPERATOR, map=args.map, version=made.version,
        detail=f"version {made.version} is version {args.version}'s bytes (twohr maps rollback)"))
    print(f"map {args.map}: version {entry.version} is version {args.version} again (byte for byte); kept "
          f"versions {', '.join(map(str, entry.versions))}; logged in {audit}")
    return 0


def _export(args: argparse.Namespace) -> int:
    from twohr.mapfile import read_map

    stored = read_map(_target(args, args.map))
    arrays, header = stored.arrays, stored.header
    source = landmark_sources(arrays)
    good = ~arrays.landmark_bad
    out = Path(args.out or f"runs/maps/{header.name}.ply")
    size = write_ply(out, arrays.landmark_positions[good], source[good])
    robots = header.camera_robots or ["?"] * (1 + len(header.cameras))
    print(f"wrote {out}: {int(good.sum())} landmarks of map {header.name} (frame {header.frame_id}), {size} bytes; "
          f"property source: " + ", ".join(f"{i} = {r or 'not recorded'}" for i, r in enumerate(robots)))
    return 0


def _remove_robot(args: argparse.Namespace) -> int:
    from twohr.audit import AuditLog
    from twohr.errors import TwohrError
    from twohr.mapfile import OPERATOR, encode_map, read_map
    from twohr.mapstore import MapStore, without_robot

    from ..supervisor import audit_file

    if not Path(args.maps).is_dir():
        raise TwohrError(f"no map store folder {args.maps}")
    store = MapStore(args.maps, parse_map_versions(args.map_versions))
    kept = without_robot(read_map(store.latest_file(args.map)), args.robot)
    audit = Path(args.audit) if args.audit else audit_file(args.maps)
    entry = store.save(encode_map(kept), args.map, builder=OPERATOR, on_saved=lambda made: AuditLog(audit).record(
        "map.remove_robot", OPERATOR, map=args.map, version=made.version, robot=args.robot,
        detail=f"robot {args.robot}'s keyframes removed (twohr maps remove-robot)"))
    print(f"map {args.map}: version {entry.version} without robot {args.robot}'s keyframes ({entry.keyframes} "
          f"keyframes, {entry.landmarks} landmarks left); logged in {audit}")
    return 0


def landmark_sources(arrays) -> np.ndarray:
    """For each landmark of a map's arrays (:class:`twohr.mapfile.MapArrays`), the camera of the first keyframe that
    observes it (``keyframe_camera``: which robot's keyframes made it), -1 for one no keyframe observes."""
    import numpy as np

    source = np.full(len(arrays.landmark_positions), -1, np.int64)
    for k in range(len(arrays.keyframe_stamps)):
        ids = arrays.keypoint_landmark[arrays.keyframe_first[k]:arrays.keyframe_first[k + 1]]
        ids = ids[ids >= 0]
        source[ids[source[ids] < 0]] = arrays.keyframe_camera[k]
    return source


def write_ply(path: str | Path, points: np.ndarray, sources: np.ndarray | None = None) -> int:
    """Points (N, 3) as a binary little-endian PLY point cloud (``sources``: an integer per point, written as
    property ``source``: which robot's keyframes made it), written atomically and private (0600: a map is the
    robots' surroundings); returns its size in bytes."""
    import numpy as np

    from twohr.files import write_atomic

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
    write_atomic(path, data, durable=True)
    return len(data)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("maps", help="saved maps: list a map store, show or verify map files",
                       description="Maps saved by `twohr run --save-map FILE` or by sessions with a map "
                       "(`twohr up --maps DIR`). A map is named by its file, or by its name in the --maps folder.")
    actions = p.add_subparsers(dest="action", required=True)
    listing = actions.add_parser("list", help="the maps in a map store folder, latest versions")
    show = actions.add_parser("show", help="one map's header: camera, detector, counts, size, provenance")
    show.add_argument("map", help="a .map file, or a map's name in --maps")
    verify = actions.add_parser("verify", help="check map files through (exit 2 if any is unusable)")
    verify.add_argument("maps_or_files", nargs="+", metavar="MAP", help=".map files or names in --maps")
    verify.add_argument("--detector-model", default=None, help="also check they were built with this detector model")
    rollback = actions.add_parser("rollback", help="make an earlier version of a map the latest again (a new "
                                  "version, the same bytes), on the folder when no stack serves it")
    rollback.add_argument("map", help="the map's name in --maps")
    rollback.add_argument("--version", type=int, required=True, help="the kept version to restore (twohr maps list)")
    rollback.add_argument("--map-versions", default=10, metavar="N", help="versions of each map to keep, as twohr "
                          "up --map-versions (default 10)")
    rollback.add_argument("--audit", default=None, metavar="FILE", help="the audit trail the rollback is appended "
                          "to (default MAPS/audit.jsonl: the stack's, as twohr up --maps MAPS and compose keep it)")
    rollback.set_defaults(func=_rollback)
    export = actions.add_parser("export", help="a map's landmarks as a point cloud for other tools (PLY)")
    export.add_argument("map", help="a .map file, or a map's name in --maps")
    export.add_argument("--ply", action="store_true", required=True, help="write a binary PLY: x y z in the map's "
                        "frame (metres), and which robot's keyframes made each point (property source)")
    export.add_argument("--out", default=None, metavar="FILE", help="the PLY file (default runs/maps/NAME.ply)")
    export.set_defaults(func=_export)
    remove = actions.add_parser("remove-robot", help="a shared map's next version without one robot's keyframes "
                                "(a revoked robot's, say), on the folder when no stack serves it")
    remove.add_argument("map", help="the map's name in --maps")
    remove.add_argument("robot", help="the robot whose keyframes go (twohr maps show MAP: camera_robots)")
    remove.add_argument("--map-versions", default=10, metavar="N", help="versions of each map to keep, as twohr "
                        "up --map-versions (default 10)")
    remove.add_argument("--audit", default=None, metavar="FILE", help="the audit trail it is appended to (default "
                        "MAPS/audit.jsonl)")
    remove.set_defaults(func=_remove_robot)
    for action in (listing, show, verify, rollback, export, remove):
        action.add_argument("--maps", default="maps", help="the map store folder (default ./maps)")
    listing.set_defaults(func=_list)
    show.set_defaults(func=_show)
    verify.set_defaults(func=_verify)
