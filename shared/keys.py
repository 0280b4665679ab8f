"""Zenoh key expressions: ``twohr/<robot_id>/<stream>``."""

from __future__ import annotations

# the robot-id pattern and reserved names live in .ids; named here too for the code that reads them as keys'
from .ids import RESERVED_ROBOT_IDS as RESERVED_ROBOT_IDS
from .ids import ROBOT_PATTERN as ROBOT_PATTERN
from .ids import ROS2_RESERVED_NAMES as ROS2_RESERVED_NAMES
from .ids import check_robot_id

PREFIX = "twohr"
#: The services a stack runs for every session, in the order it starts them: the gateway starts a session only while
#: each is up, and fails the sessions that need one that stops (one on a robot's own tracker needs none of the
#: stack's trackers); the ros2 bridge is optional.
PIPELINE_SERVICES = ("source", "detector", "yolo", "matcher", "tracker", "mapserver", "recorder")
#: The services that answer the tracker's keyframe jobs: any number of replicas each, on any host of the mesh.
NETWORK_SERVICES = ("detector", "yolo", "matcher")
#: Data streams every robot publishes.
STREAMS = ("frames", "keypoints", "dynamics", "matches", "pose", "landmarks", "path", "status", "keyframes")
#: Control and request keys (not recorded as data streams).
CONTROL = "control"
MATCH_QUERY = "rpc/match"
DETECT_QUERY = "rpc/detect"
DYNAMICS_QUERY = "rpc/dynamics"
RAW_CAMERA = "camera"
#: the session id a camera driver puts on frames it publishes; the source relay replaces it with the live session's
LIVE_SESSION = "live"
#: every service process (a replica) answers a health query on ``twohr/_health/<name>/<replica>`` with its counters
HEALTH_PREFIX = f"{PREFIX}/_health"
#: every service process holds a liveliness token ``twohr/_alive/<name>/<replica>`` while it is connected
ALIVE_PREFIX = f"{PREFIX}/_alive"

#: a robot's map snapshot (:func:`snapshot_key`): a key of its own depth, which ``twohr/*/*`` (the recorder, the
#: live view) does not match
SNAPSHOT = "map/snapshot"
#: the map room's store answers ``twohr/maps/<name>`` with a map file's bytes, and keeps the bytes a query on
#: ``twohr/maps/<name>/save`` carries as the map's next version (the protocol: :mod:`twohr.mapclient`)
MAPS_PREFIX = f"{PREFIX}/maps"
#: what each key carries, by the name above that makes it (a robot's stream or query, or a prefix); the key table of
#: the documentation (docs/hooks.py) is made from these names, this text and the roles' grants
CARRIES = {
    CONTROL: "`ControlMsg`: start or stop a session, with its full config",
    RAW_CAMERA: "`FrameMsg`: raw frames from any camera driver, relayed by the source in a live session",
    "frames": "`FrameMsg`: RGB (JPEG/PNG bytes as on disk) + 16-bit depth + intrinsics",
    "keypoints": "`KeypointsMsg`: xy, descriptors, scores",
    "dynamics": "`DynamicsMsg`: boxes, classes, the dynamic mask (PNG)",
    "matches": "`MatchesMsg`: every match result",
    "pose": "`PoseMsg`: camera-to-world pose, tracking status, inliers",
    "landmarks": "`LandmarksMsg`: the map points (world xyz), whenever a keyframe changed the map",
    "path": "`PathMsg`: live corrections, the keyframes that are new or moved (the whole path every 10th message; "
            "`PathAssembler` rebuilds it); at the end the refined trajectory",
    "status": "`StatusMsg`: session lifecycle (frames relayed, for a camera session); the tracker's health and, at "
              "a session's end, its keyframe jobs' latency; `error` from any service that cannot run the session",
    MATCH_QUERY: "query to one replica: descriptors A, B (`MatchRequestMsg`; B may hold several sets, a "
                 "relocalisation's candidates) → matches (`MatchesMsg`, per set)",
    DETECT_QUERY: "query to one replica: a frame message → its 2HR keypoints (also published on `keypoints`)",
    DYNAMICS_QUERY: "query to one replica: a frame message → its fresh dynamic mask (also published on `dynamics`)",
    HEALTH_PREFIX: "query: a service process's counters, its replica name and host",
    ALIVE_PREFIX: "liveliness token, held while the process is connected",
    MAPS_PREFIX: "query: a map file's bytes from the map room's store (the map server)",
    SNAPSHOT: "a map file's bytes: the tracker's latest copy of the session's map, every few seconds (the map room "
              "keeps it, and answers a query on it for the tracker a session moves to when its own died)",
    f"{MAPS_PREFIX}/save": "query carrying a map file: the map store keeps it as the map's next version",
    "keyframes": "`KeyframesMsg`: a robot's new keyframes for the map server, in a session that shares a map",
    f"{MAPS_PREFIX}/merged": "`MergeMsg`: a robot placed in a shared map's frame (merged, or the map's first robot)",
}



def map_key(name: str, save: bool = False) -> str:
    """The key to read map ``name`` from the map store, or (``save``) to save it there."""
    return f"{MAPS_PREFIX}/{name}" + ("/save" if save else "")


def parse_map_key(key_expr: str, save: bool = False) -> str:
    """The map name in a key made by :func:`map_key`; ValueError for a key that names no single map."""
    parts = str(key_expr).split("/")
    name = parts[2] if len(parts) > 2 else ""
    if str(key_expr) != map_key(name, save) or not name or "*" in name:
        raise ValueError(f"{key_expr}: name one map, {map_key('<name>', save)}")
    return name


def merged_key(name: str = "*") -> str:
    """The key of shared map ``name``'s merge events (``*``: of every map)."""
    return f"{map_key(name)}/merged"


def snapshot_key(robot_id: str = "*") -> str:
    """The key of a robot's map snapshot (``*``: of every robot): the tracker's latest copy of the session's map,
    which the map room keeps outside the tracker's process and hands to the tracker a session moves to."""
    return f"{PREFIX}/{robot_id}/{SNAPSHOT}"


def alive_key(service: str, replica: str = "*") -> str:
    """The liveliness token of one replica of ``service`` (``*``: of every replica)."""
    return f"{ALIVE_PREFIX}/{service}/{replica}"


def health_key(service: str, replica: str = "*") -> str:
    """The health query key of one replica of ``service`` (``*``: of every replica)."""
    return f"{HEALTH_PREFIX}/{service}/{replica}"


def parse_replica_key(key_expr: str) -> tuple[str, str]:
    """(service, replica) of a key made by :func:`alive_key` or :func:`health_key`."""
    parts = str(key_expr).split("/")
    if len(parts) != 4 or parts[0] != PREFIX or f"{PREFIX}/{parts[1]}" not in (ALIVE_PREFIX, HEALTH_PREFIX):
        raise ValueError(f"not a replica key: {key_expr}")
    return parts[2], parts[3]


#: the tracker replica name of a robot's own tracker (``twohr camera --edge``): ``edge+<robot>``; a service's
#: replica name (:func:`twohr.service.replica_id`) never holds a ``+``, so no stack process can pass for one
EDGE_MARK = "edge+"


def edge_replica(robot_id: str) -> str:
    """The tracker replica name of robot ``robot_id``'s own tracker."""
    key(robot_id, "pose")  # a valid robot id
    return f"{EDGE_MARK}{robot_id}"


def edge_robot(replica: str) -> str | None:
    """The robot whose own tracker ``replica`` is, or None for a tracker of the stack."""
    return replica[len(EDGE_MARK):] if replica.startswith(EDGE_MARK) else None


def replica_query(robot_id: str, query: str, replica: str) -> str:
    """The key a network query for ``robot_id`` goes to when one replica is to answer it,
    e.g. ``twohr/robot1/rpc/detect/host-4711``."""
    return f"{key(robot_id, query)}/{replica}"


def key(robot_id: str, stream: str) -> str:
    """The key of one robot's stream, e.g. ``twohr/robot1/pose``."""
    return f"{PREFIX}/{check_robot_id(robot_id)}/{stream}"


def all_robots(stream: str) -> str:
    """The key expression matching one stream of every robot, e.g. ``twohr/*/pose``."""
    return f"{PREFIX}/*/{stream}"


def parse(key_expr: str) -> tuple[str, str]:
    """``twohr/<robot>/<stream...>`` -> (robot, stream)."""
    parts = str(key_expr).split("/", 2)
    if len(parts) != 3 or parts[0] != PREFIX:
        raise ValueError(f"not a twohr key: {key_expr}")
    return parts[1], parts[2]
