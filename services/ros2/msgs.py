"""The ROS 2 messages twohr speaks, from rosbags' typestore (ROS 2 Jazzy definitions; Humble's are the same).

Each message class is a rosbags dataclass: every field is required, primitive arrays and ``uint8[]`` are numpy
arrays, ``__msgtype__`` names the ROS type. rosbags also gives the RIHS01 type hash (REP 2011) and the CDR codec.
"""

from __future__ import annotations

import math
from functools import cache

from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_typestore

from twohr.messages import MessageError

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
_TYPES = TYPESTORE.types

Time = _TYPES["builtin_interfaces/msg/Time"]
Header = _TYPES["std_msgs/msg/Header"]
Point = _TYPES["geometry_msgs/msg/Point"]
Vector3 = _TYPES["geometry_msgs/msg/Vector3"]
Quaternion = _TYPES["geometry_msgs/msg/Quaternion"]
Pose = _TYPES["geometry_msgs/msg/Pose"]
PoseStamped = _TYPES["geometry_msgs/msg/PoseStamped"]
PoseWithCovariance = _TYPES["geometry_msgs/msg/PoseWithCovariance"]
Twist = _TYPES["geometry_msgs/msg/Twist"]
TwistWithCovariance = _TYPES["geometry_msgs/msg/TwistWithCovariance"]
Odometry = _TYPES["nav_msgs/msg/Odometry"]
Transform = _TYPES["geometry_msgs/msg/Transform"]
TransformStamped = _TYPES["geometry_msgs/msg/TransformStamped"]
TFMessage = _TYPES["tf2_msgs/msg/TFMessage"]
Path = _TYPES["nav_msgs/msg/Path"]
Image = _TYPES["sensor_msgs/msg/Image"]
CompressedImage = _TYPES["sensor_msgs/msg/CompressedImage"]
RegionOfInterest = _TYPES["sensor_msgs/msg/RegionOfInterest"]
CameraInfo = _TYPES["sensor_msgs/msg/CameraInfo"]
KeyValue = _TYPES["diagnostic_msgs/msg/KeyValue"]
DiagnosticStatus = _TYPES["diagnostic_msgs/msg/DiagnosticStatus"]
DiagnosticArray = _TYPES["diagnostic_msgs/msg/DiagnosticArray"]


class CdrError(MessageError):
    """A payload that is not valid CDR for the expected type."""


def dds_type(cls: type) -> str:
    """The DDS/rmw type name, e.g. ``geometry_msgs::msg::dds_::PoseStamped_``."""
    package, kind, name = cls.__msgtype__.split("/")
    return f"{package}::{kind}::dds_::{name}_"


@cache
def type_hash(cls: type) -> str:
    """The type's RIHS01 hash, as ``ros2 topic info -v`` shows it and rmw_zenoh puts it in keys."""
    return TYPESTORE.hash_rihs01(cls.__msgtype__)


def stamp(seconds: float) -> Time:
    """A ``Time`` from seconds since the epoch, exact to the nanosecond."""
    # whole seconds apart: ``seconds * 1e9`` of an epoch stamp is off by up to 128 ns in float64
    whole = math.floor(seconds)
    nanoseconds = whole * 1_000_000_000 + round((seconds - whole) * 1e9)
    return Time(sec=nanoseconds // 1_000_000_000, nanosec=nanoseconds % 1_000_000_000)


def seconds(time: Time) -> float:
    return time.sec + time.nanosec * 1e-9


def serialize(message) -> bytes:
    """The CDR payload of a message (little-endian, encapsulation header included)."""
    return bytes(TYPESTORE.serialize_cdr(message, message.__msgtype__, little_endian=True))


def deserialize(cls: type, data: bytes | bytearray | memoryview):
    """Parse a CDR payload as ``cls``; raises :class:`CdrError` on any malformed input."""
    try:
        return TYPESTORE.deserialize_cdr(data, cls.__msgtype__)
    except SerdeError as exc:
        raise CdrError(f"{cls.__msgtype__}: {exc}") from None
