"""The ros2 service: twohr as a ROS 2 node on rmw_zenoh, with no ROS installed.

Out: every pose on ``twohr/<robot>/pose`` is published as ``geometry_msgs/PoseStamped`` (map frame),
``nav_msgs/Odometry`` (odom -> camera), ``tf2_msgs/TFMessage`` (map -> odom and odom -> camera, REP 105)
and, at keyframes, ``nav_msgs/Path``; the tracker's corrections on ``twohr/<robot>/path`` as
``nav_msgs/Path`` on ``path_corrected``, and as the map -> odom transform; every session status on
``twohr/<robot>/status`` (the tracker's ``ok``/``degraded`` and why) as ``diagnostic_msgs/DiagnosticArray``
on ``/diagnostics``. All in CDR on rmw_zenoh's key expressions with its attachments; each robot is a
node (``twohr`` in namespace ``/<robot>`` by default) announced with rmw_zenoh's liveliness tokens, so
``ros2 topic list`` / ``ros2 topic echo`` on an rmw_zenoh host see it.

In (optional, ``--input-robot``): a ROS 2 camera's colour ``Image``/``CompressedImage``, aligned
depth ``Image`` and ``CameraInfo`` are paired by stamp and republished as twohr frames on
``twohr/<robot>/camera``, where the source relays them into a live session.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from collections.abc import Iterator

import zenoh
from pydantic import ValidationError

from twohr import keys
from twohr.bus import BusConfig, bus_from_args
from twohr.config import read_yaml_mapping
from twohr.errors import ConfigError, validation_problems
from twohr.messages import MergeMsg, PathAssembler, PathMsg, PoseMsg, StatusMsg, decode, encode
from twohr.service import Service, declare_publisher, one_line_errors, service_parser

from . import msgs
from .config import Ros2Config
from .convert import CameraAssembler, PoseOutputs, diagnostics
from .rmw import Attachment, NodeInfo, make_gid, topic_key, topic_key_any_hash

#: the camera input's roles and the message type each is subscribed with
CAMERA_ROLES: tuple[tuple[str, type], ...] = (
    ("color", msgs.Image), ("color_compressed", msgs.CompressedImage), ("depth", msgs.Image), ("info", msgs.CameraInfo))


class RosNode:
    """One ROS 2 node of this Zenoh session: its liveliness tokens and its publishers, each with a GID and a
    sequence counter for the attachments. Node and entity ids come from one counter per session, as in rmw_zenoh."""

    def __init__(self, session: zenoh.Session, info: NodeInfo, entity_ids: Iterator[int]) -> None:
        self.session = session
        self.info = info
        self.entity_ids = entity_ids
        self.tokens = [session.liveliness().declare_token(info.node_token())]
        self.publishers: dict[str, tuple[zenoh.Publisher, bytes, list[int]]] = {}

    def _entity(self, kind: str, topic: str, cls: type) -> str:
        token = self.info.endpoint_token(next(self.entity_ids), kind, topic, cls)
        self.tokens.append(self.session.liveliness().declare_token(token))
        return token

    def subscription(self, topic: str, cls: type) -> None:
        """Announce a subscription (the data subscriber itself is declared by the service shell)."""
        self._entity("MS", topic, cls)

    def publish(self, topic: str, message) -> None:
        if topic not in self.publishers:
            token = self._entity("MP", topic, type(message))
            publisher = declare_publisher(self.session, topic_key(self.info.domain_id, topic, type(message)),
                                          wait_for_subscribers=0.5)
            self.publishers[topic] = (publisher, make_gid(token), [0])
        publisher, gid, sequence = self.publishers[topic]
        sequence[0] += 1
        attachment = Attachment(sequence_number=sequence[0], source_timestamp_ns=time.time_ns(), source_gid=gid)
        publisher.put(msgs.serialize(message), attachment=attachment.encode())

    def close(self) -> None:
        for publisher, _, _ in self.publishers.values():
            publisher.undeclare()
        for token in self.tokens:
            token.undeclare()


class Ros2Service(Service):
    name = "ros2"

    def __init__(self, bus: BusConfig | None = None, config: Ros2Config | None = None) -> None:
        super().__init__(bus, queue_size=64, policy="drop_oldest")
        self.config = config or Ros2Config(enabled=True)
        self.outputs = PoseOutputs(self.config)
        self.paths = PathAssembler()
        self.nodes: dict[str, RosNode] = {}  # by namespace
        self.entity_ids = itertools.count()
        self.published: dict[str, int] = {}
        self.camera = CameraAssembler(self.config.camera_input) if self.config.camera_input else None
        self.inputs: dict[str, tuple[str, type]] = {}  # key prefix -> (role, type)
        if self.config.camera_input:
            topics = self.config.camera_input.topics()
            for role, cls in CAMERA_ROLES:
                prefix = topic_key_any_hash(self.config.domain_id, topics[role], cls)[:-1]
                self.inputs[prefix] = (role, cls)

    def subscriptions(self) -> list[str]:
        return ([keys.all_robots("pose"), keys.all_robots("path"), keys.all_robots("status"), keys.merged_key()]
                + [prefix + "*" for prefix in self.inputs])

    def _node(self, namespace: str) -> RosNode:
        if namespace not in self.nodes:
            info = NodeInfo(domain_id=self.config.domain_id, session_id=str(self.session.zid()),
                            node_id=next(self.entity_ids), namespace=namespace, name=self.config.node_name)
            self.nodes[namespace] = RosNode(self.session, info, self.entity_ids)
        return self.nodes[namespace]

    def on_start(self) -> None:
        camera = self.config.camera_input
        if camera:
            node = self._node(camera.namespace.rstrip("/") or "/")
            topics = camera.topics()
            for role, cls in CAMERA_ROLES:
                node.subscription(topics[role], cls)

    def handle(self, key: str, payload: bytes) -> None:
        if key.startswith(keys.PREFIX + "/"):
            if key.startswith(keys.MAPS_PREFIX + "/"):  # a robot merged into a shared map
                merge, _ = decode(payload, MergeMsg)
                robot, outputs = merge.robot_id, self.outputs.merge(merge)
            elif key.endswith("/path"):
                path, arrays = decode(payload, PathMsg)
                trajectory = self.paths.add(path, arrays)  # the whole path, rebuilt from deltas
                if trajectory is None:
                    return  # a delta was lost: the next full path brings it back
                robot, outputs = path.robot_id, self.outputs.corrections(path, trajectory)
            elif key.endswith("/status"):
                status, _ = decode(payload, StatusMsg)
                robot, outputs = status.robot_id, [diagnostics(status, self.config)]
            else:
                pose, _ = decode(payload, PoseMsg)
                robot, outputs = pose.robot_id, self.outputs.messages(pose)
            node = self._node(self.config.robot_namespace(robot))
            for topic, message in outputs:
                node.publish(topic, message)
                self.published[message.__msgtype__] = self.published.get(message.__msgtype__, 0) + 1
            return
        prefix = key[: key.rfind("/") + 1]
        if prefix not in self.inputs:
            return
        role, cls = self.inputs[prefix]
        message = msgs.deserialize(cls, payload)
        assert self.camera is not None
        if role == "info":
            self.camera.add_info(message)
            return
        frame = self.camera.add_depth(message) if role == "depth" else self.camera.add_color(message)
        if frame is not None:
            header, arrays = frame
            header = header.model_copy(update={"sent_at": time.time()})
            self.publish(keys.key(header.robot_id, keys.RAW_CAMERA),
                         encode(header, arrays, {"rgb": "jpeg", "depth": "png"}))

    def health(self) -> dict:
        out = {**super().health(), "published": dict(self.published),
               "corrections": {robot: state.corrections for robot, state in self.outputs.robots.items()}}
        if self.camera is not None:
            out["camera"] = {"frames": self.camera.frames, "unpaired": self.camera.unpaired,
                             "without_camera_info": self.camera.without_info}
        return out

    def run(self, stop=None) -> None:
        try:
            super().run(stop)
        finally:
            for node in self.nodes.values():
                node.close()
            self.nodes.clear()


def command(router: str | None = None, domain_id: int = 0, extra: list[str] | None = None) -> list[str]:
    """The command line that starts this service as a process, for ``twohr up``."""
    return [sys.executable, "-m", "twohr_services.ros2", *(["--router", router] if router else []),
            "--domain", str(domain_id), *(extra or [])]


def load_config(args: argparse.Namespace) -> Ros2Config:
    """The service's config: ``--config`` (YAML/JSON) first, then the flags that were given.
    Raises ValueError with a one-line reason."""
    data: dict = {}
    if args.config:
        try:
            data = read_yaml_mapping(args.config, "ros2 settings")
        except ConfigError as exc:
            raise ValueError(str(exc).splitlines()[0]) from None
        data = data.get("ros2", data)
    for name in ("domain_id", "namespace", "node_name", "map_frame", "odom_frame", "camera_frame"):
        if getattr(args, name) is not None:
            data[name] = getattr(args, name)
    if args.input_robot:
        data["camera_input"] = {**(data.get("camera_input") or {}), "robot_id": args.input_robot,
                                **({"namespace": args.input_namespace} if args.input_namespace else {})}
    data["enabled"] = True
    try:
        return Ros2Config.model_validate(data)
    except ValidationError as exc:
        raise ValueError(validation_problems(exc)) from None


@one_line_errors("ros2")
def main(argv: list[str] | None = None) -> None:
    parser = service_parser("ros2", __doc__)
    parser.add_argument("--config", help="YAML or JSON file with the ros2 settings (a top-level 'ros2' key or not)")
    parser.add_argument("--domain", dest="domain_id", type=int, help="ROS_DOMAIN_ID (default 0)")
    parser.add_argument("--namespace", help="ROS namespace of each robot; {robot} is the robot id (default /{robot})")
    parser.add_argument("--node-name", help="ROS node name (default twohr)")
    parser.add_argument("--map-frame", help="frame id of the corrected poses (default map)")
    parser.add_argument("--odom-frame", help="frame id of the online, drifting poses (default odom)")
    parser.add_argument("--camera-frame", help="child frame id of the camera (default camera)")
    parser.add_argument("--input-robot", help="relay a ROS 2 camera into twohr/<ROBOT>/camera")
    parser.add_argument("--input-namespace", help="ROS namespace of that camera's topics (default /)")
    args = parser.parse_args(argv)
    try:
        config = load_config(args)
    except ValueError as exc:
        parser.error(str(exc))  # one line, exit code 2
    bus = bus_from_args(args)
    Ros2Service(bus, config).run_forever()

