"""A ROS 2 bag as one MCAP file: profile ``ros2``, schemas in ``ros2msg`` text, messages in CDR.

``ros2 bag`` (rosbag2_storage_mcap) and rosbags read it as it is. The recorder can keep one per
session next to its own MCAP: :meth:`Ros2BagWriter.write_pose` records the same PoseStamped,
Odometry, TF and Path messages that the ros2 service publishes live.
"""

from __future__ import annotations

import time
from pathlib import Path as FilePath

from mcap.writer import CompressionType, Writer

from ..messages import PoseMsg
from . import msgs
from .config import Ros2Config
from .convert import PoseOutputs

#: rosbag2's QoS metadata for a reliable, volatile, keep-last publisher (what ``ros2 bag play`` offers again)
_QOS = ("- history: 1\n  depth: 10\n  reliability: 1\n  durability: 2\n  deadline:\n    sec: 0\n    nsec: 0\n"
        "  lifespan:\n    sec: 0\n    nsec: 0\n  liveliness: 1\n  liveliness_lease_duration:\n    sec: 0\n"
        "    nsec: 0\n  avoid_ros_namespace_conventions: false\n")


class Ros2BagWriter:
    """Writes ROS 2 messages into ``path`` (a ``.mcap`` file); call :meth:`close` to finish it."""

    def __init__(self, path: str | FilePath, config: Ros2Config | None = None) -> None:
        self.path = FilePath(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.file = open(self.path, "wb")  # noqa: SIM115 (closed in close())
        self.writer = Writer(self.file, compression=CompressionType.ZSTD)
        self.writer.start(profile="ros2", library="twohr")
        self.outputs = PoseOutputs(config or Ros2Config())
        self.schemas: dict[str, int] = {}
        self.channels: dict[str, int] = {}
        self.counts: dict[str, int] = {}
        self.closed = False

    def _channel(self, topic: str, cls: type[msgs.RosMessage]) -> int:
        if topic not in self.channels:
            if cls.ros_type not in self.schemas:
                self.schemas[cls.ros_type] = self.writer.register_schema(
                    cls.ros_type, "ros2msg", msgs.message_definition(cls).encode())
            self.channels[topic] = self.writer.register_channel(
                topic, "cdr", self.schemas[cls.ros_type], metadata={"offered_qos_profiles": _QOS})
        return self.channels[topic]

    def write(self, topic: str, message: msgs.RosMessage, log_time_ns: int | None = None) -> None:
        """Record one message on a fully qualified topic, logged at ``log_time_ns`` (default: now)."""
        channel = self._channel(topic, type(message))
        log_time = time.time_ns() if log_time_ns is None else log_time_ns
        self.counts[topic] = self.counts.get(topic, 0) + 1
        self.writer.add_message(channel, log_time=log_time, data=msgs.serialize(message), publish_time=log_time,
                                sequence=self.counts[topic])

    def write_pose(self, pose: PoseMsg, log_time_ns: int | None = None) -> None:
        """Record a twohr pose as PoseStamped, Odometry, TF and (at keyframes) Path, stamped with the sensor time
        unless ``log_time_ns`` is given."""
        log_time = round(pose.stamp * 1e9) if log_time_ns is None else log_time_ns
        for topic, message in self.outputs.messages(pose):
            self.write(topic, message, log_time)

    def close(self) -> None:
        """Write the summary and footer: the file is then a complete, indexed MCAP."""
        if not self.closed:
            self.writer.finish()
            self.file.close()
            self.closed = True

    def __enter__(self) -> Ros2BagWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
