"""The ROS 2 messages twohr speaks, as pydantic models driven by their ``.msg`` definitions.

Each model names its ROS type, its official RIHS01 type hash (REP 2011, checked against the
published values in the tests) and its field list in ``.msg`` syntax. That one definition drives
the CDR encoder, the decoder and the ``ros2msg`` schema text written into ROS 2 MCAP files.
"""

from __future__ import annotations

import math
import re
import struct
from functools import cache
from typing import ClassVar, TypeVar

from pydantic import BaseModel, Field

from .cdr import PRIMITIVES, CdrError, CdrReader, CdrWriter


class RosMessage(BaseModel):
    """Base of the ROS 2 message models. Field order is the order of ``definition``."""

    ros_type: ClassVar[str] = ""
    type_hash: ClassVar[str] = ""
    definition: ClassVar[str] = ""

    @classmethod
    def dds_type(cls) -> str:
        """The DDS/rmw type name, e.g. ``geometry_msgs::msg::dds_::PoseStamped_``."""
        package, kind, name = cls.ros_type.split("/")
        return f"{package}::{kind}::dds_::{name}_"


class Time(RosMessage):
    ros_type: ClassVar[str] = "builtin_interfaces/msg/Time"
    type_hash: ClassVar[str] = "RIHS01_b106235e25a4c5ed35098aa0a61a3ee9c9b18d197f398b0e4206cea9acf9c197"
    definition: ClassVar[str] = "int32 sec\nuint32 nanosec"
    sec: int = 0
    nanosec: int = Field(0, ge=0, lt=1_000_000_000)

    @classmethod
    def from_seconds(cls, seconds: float) -> Time:
        # whole seconds apart: ``seconds * 1e9`` of an epoch stamp is off by up to 128 ns in float64
        whole = math.floor(seconds)
        nanoseconds = whole * 1_000_000_000 + round((seconds - whole) * 1e9)
        return cls(sec=nanoseconds // 1_000_000_000, nanosec=nanoseconds % 1_000_000_000)

    def seconds(self) -> float:
        return self.sec + self.nanosec * 1e-9


class Header(RosMessage):
    ros_type: ClassVar[str] = "std_msgs/msg/Header"
    type_hash: ClassVar[str] = "RIHS01_f49fb3ae2cf070f793645ff749683ac6b06203e41c891e17701b1cb597ce6a01"
    definition: ClassVar[str] = "builtin_interfaces/msg/Time stamp\nstring frame_id"
    stamp: Time = Field(default_factory=Time)
    frame_id: str = ""


class Point(RosMessage):
    ros_type: ClassVar[str] = "geometry_msgs/msg/Point"
    definition: ClassVar[str] = "float64 x\nfloat64 y\nfloat64 z"
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0


class Vector3(RosMessage):
    ros_type: ClassVar[str] = "geometry_msgs/msg/Vector3"
    definition: ClassVar[str] = "float64 x\nfloat64 y\nfloat64 z"
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0


class Quaternion(RosMessage):
    ros_type: ClassVar[str] = "geometry_msgs/msg/Quaternion"
    definition: ClassVar[str] = "float64 x\nfloat64 y\nfloat64 z\nfloat64 w"
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    w: float = 1.0


class Pose(RosMessage):
    ros_type: ClassVar[str] = "geometry_msgs/msg/Pose"
    definition: ClassVar[str] = "geometry_msgs/msg/Point position\ngeometry_msgs/msg/Quaternion orientation"
    position: Point = Field(default_factory=Point)
    orientation: Quaternion = Field(default_factory=Quaternion)


class PoseStamped(RosMessage):
    ros_type: ClassVar[str] = "geometry_msgs/msg/PoseStamped"
    type_hash: ClassVar[str] = "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8"
    definition: ClassVar[str] = "std_msgs/msg/Header header\ngeometry_msgs/msg/Pose pose"
    header: Header = Field(default_factory=Header)
    pose: Pose = Field(default_factory=Pose)


class PoseWithCovariance(RosMessage):
    ros_type: ClassVar[str] = "geometry_msgs/msg/PoseWithCovariance"
    definition: ClassVar[str] = "geometry_msgs/msg/Pose pose\nfloat64[36] covariance"
    pose: Pose = Field(default_factory=Pose)
    covariance: list[float] = Field(default_factory=lambda: [0.0] * 36, min_length=36, max_length=36)


class Twist(RosMessage):
    ros_type: ClassVar[str] = "geometry_msgs/msg/Twist"
    definition: ClassVar[str] = "geometry_msgs/msg/Vector3 linear\ngeometry_msgs/msg/Vector3 angular"
    linear: Vector3 = Field(default_factory=Vector3)
    angular: Vector3 = Field(default_factory=Vector3)


class TwistWithCovariance(RosMessage):
    ros_type: ClassVar[str] = "geometry_msgs/msg/TwistWithCovariance"
    definition: ClassVar[str] = "geometry_msgs/msg/Twist twist\nfloat64[36] covariance"
    twist: Twist = Field(default_factory=Twist)
    covariance: list[float] = Field(default_factory=lambda: [0.0] * 36, min_length=36, max_length=36)


class Odometry(RosMessage):
    ros_type: ClassVar[str] = "nav_msgs/msg/Odometry"
    type_hash: ClassVar[str] = "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0"
    definition: ClassVar[str] = (
        "std_msgs/msg/Header header\nstring child_frame_id\n"
        "geometry_msgs/msg/PoseWithCovariance pose\ngeometry_msgs/msg/TwistWithCovariance twist"
    )
    header: Header = Field(default_factory=Header)
    child_frame_id: str = ""
    pose: PoseWithCovariance = Field(default_factory=PoseWithCovariance)
    twist: TwistWithCovariance = Field(default_factory=TwistWithCovariance)


class Transform(RosMessage):
    ros_type: ClassVar[str] = "geometry_msgs/msg/Transform"
    definition: ClassVar[str] = "geometry_msgs/msg/Vector3 translation\ngeometry_msgs/msg/Quaternion rotation"
    translation: Vector3 = Field(default_factory=Vector3)
    rotation: Quaternion = Field(default_factory=Quaternion)


class TransformStamped(RosMessage):
    ros_type: ClassVar[str] = "geometry_msgs/msg/TransformStamped"
    type_hash: ClassVar[str] = "RIHS01_0a241f87d04668d94099cbb5ba11691d5ad32c2f29682e4eb5653424bd275206"
    definition: ClassVar[str] = ("std_msgs/msg/Header header\nstring child_frame_id\n"
                                 "geometry_msgs/msg/Transform transform")
    header: Header = Field(default_factory=Header)
    child_frame_id: str = ""
    transform: Transform = Field(default_factory=Transform)


class TFMessage(RosMessage):
    ros_type: ClassVar[str] = "tf2_msgs/msg/TFMessage"
    type_hash: ClassVar[str] = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
    definition: ClassVar[str] = "geometry_msgs/msg/TransformStamped[] transforms"
    transforms: list[TransformStamped] = Field(default_factory=list)


class Path(RosMessage):
    ros_type: ClassVar[str] = "nav_msgs/msg/Path"
    type_hash: ClassVar[str] = "RIHS01_1957a5bb3cee5da65c4e52e52b65a93df227efce4c20f8458b36e73066ca334b"
    definition: ClassVar[str] = "std_msgs/msg/Header header\ngeometry_msgs/msg/PoseStamped[] poses"
    header: Header = Field(default_factory=Header)
    poses: list[PoseStamped] = Field(default_factory=list)


class Image(RosMessage):
    ros_type: ClassVar[str] = "sensor_msgs/msg/Image"
    type_hash: ClassVar[str] = "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47"
    definition: ClassVar[str] = ("std_msgs/msg/Header header\nuint32 height\nuint32 width\nstring encoding\n"
                                 "uint8 is_bigendian\nuint32 step\nuint8[] data")
    header: Header = Field(default_factory=Header)
    height: int = Field(0, ge=0)
    width: int = Field(0, ge=0)
    encoding: str = ""
    is_bigendian: int = Field(0, ge=0, le=1)
    step: int = Field(0, ge=0, description="row length in bytes")
    data: bytes = b""


class CompressedImage(RosMessage):
    ros_type: ClassVar[str] = "sensor_msgs/msg/CompressedImage"
    type_hash: ClassVar[str] = "RIHS01_15640771531571185e2efc8a100baf923961a4d15d5569652e6cb6691e8e371a"
    definition: ClassVar[str] = "std_msgs/msg/Header header\nstring format\nuint8[] data"
    header: Header = Field(default_factory=Header)
    format: str = Field("", description="e.g. 'jpeg', 'png' or 'rgb8; jpeg compressed bgr8'")
    data: bytes = b""


class RegionOfInterest(RosMessage):
    ros_type: ClassVar[str] = "sensor_msgs/msg/RegionOfInterest"
    definition: ClassVar[str] = "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify"
    x_offset: int = 0
    y_offset: int = 0
    height: int = 0
    width: int = 0
    do_rectify: bool = False


class CameraInfo(RosMessage):
    ros_type: ClassVar[str] = "sensor_msgs/msg/CameraInfo"
    type_hash: ClassVar[str] = "RIHS01_b3dfd68ff46c9d56c80fd3bd4ed22c7a4ddce8c8348f2f59c299e73118e7e275"
    definition: ClassVar[str] = (
        "std_msgs/msg/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\n"
        "float64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\n"
        "sensor_msgs/msg/RegionOfInterest roi"
    )
    header: Header = Field(default_factory=Header)
    height: int = Field(0, ge=0)
    width: int = Field(0, ge=0)
    distortion_model: str = ""
    d: list[float] = Field(default_factory=list)
    k: list[float] = Field(default_factory=lambda: [0.0] * 9, min_length=9, max_length=9)
    r: list[float] = Field(default_factory=lambda: [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], min_length=9, max_length=9)
    p: list[float] = Field(default_factory=lambda: [0.0] * 12, min_length=12, max_length=12)
    binning_x: int = 0
    binning_y: int = 0
    roi: RegionOfInterest = Field(default_factory=RegionOfInterest)


class KeyValue(RosMessage):
    ros_type: ClassVar[str] = "diagnostic_msgs/msg/KeyValue"
    definition: ClassVar[str] = "string key\nstring value"
    key: str = ""
    value: str = ""


class DiagnosticStatus(RosMessage):
    """One component's state; ``level`` is one of the constants below (``byte`` on the wire)."""

    ros_type: ClassVar[str] = "diagnostic_msgs/msg/DiagnosticStatus"
    definition: ClassVar[str] = ("byte level\nstring name\nstring message\nstring hardware_id\n"
                                 "diagnostic_msgs/msg/KeyValue[] values")
    OK: ClassVar[int] = 0
    WARN: ClassVar[int] = 1
    ERROR: ClassVar[int] = 2
    STALE: ClassVar[int] = 3
    level: int = Field(0, ge=0, le=255)
    name: str = ""
    message: str = ""
    hardware_id: str = ""
    values: list[KeyValue] = Field(default_factory=list)


class DiagnosticArray(RosMessage):
    ros_type: ClassVar[str] = "diagnostic_msgs/msg/DiagnosticArray"
    type_hash: ClassVar[str] = "RIHS01_5a8a36efb05fb25070fa0fb3810290c0e6cd4862b54a8fb975a1ee8dc55a333e"
    definition: ClassVar[str] = "std_msgs/msg/Header header\ndiagnostic_msgs/msg/DiagnosticStatus[] status"
    header: Header = Field(default_factory=Header)
    status: list[DiagnosticStatus] = Field(default_factory=list)


#: every model, by ROS type name
TYPES: dict[str, type[RosMessage]] = {
    cls.ros_type: cls
    for cls in (Time, Header, Point, Vector3, Quaternion, Pose, PoseStamped, PoseWithCovariance, Twist,
                TwistWithCovariance, Odometry, Transform, TransformStamped, TFMessage, Path, Image,
                CompressedImage, RegionOfInterest, CameraInfo, KeyValue, DiagnosticStatus, DiagnosticArray)
}

_FIELD = re.compile(r"^(?P<type>[A-Za-z0-9_/]+)(?:\[(?P<size>\d*)\])?\s+(?P<name>[a-z][a-z0-9_]*)$")
M = TypeVar("M", bound=RosMessage)


@cache
def fields(cls: type[RosMessage]) -> tuple[tuple[str, str, int | None], ...]:
    """``(type, name, array)`` per field; ``array`` is None for a scalar, 0 for a sequence, N for ``T[N]``."""
    out = []
    for line in cls.definition.splitlines():
        match = _FIELD.match(line.strip())
        if not match:
            raise ValueError(f"{cls.ros_type}: cannot parse field {line!r}")
        size = match["size"]
        out.append((match["type"], match["name"], None if size is None else int(size or 0)))
    return tuple(out)


def _write(writer: CdrWriter, kind: str, value) -> None:
    if kind == "string":
        writer.string(value)
    elif kind in PRIMITIVES:
        writer.primitive(kind, value)
    else:
        _write_message(writer, value)


def _write_message(writer: CdrWriter, message: RosMessage) -> None:
    for kind, name, array in fields(type(message)):
        value = getattr(message, name)
        if array is None:
            _write(writer, kind, value)
            continue
        if array == 0:
            if kind == "uint8":
                writer.blob(bytes(value))
                continue
            writer.primitive("uint32", len(value))
        elif len(value) != array:
            raise ValueError(f"{message.ros_type}.{name}: {len(value)} values for a [{array}] array")
        if kind in PRIMITIVES and kind not in ("bool", "char", "byte"):
            writer.primitives(kind, value)
        else:
            for item in value:
                _write(writer, kind, item)


def serialize(message: RosMessage) -> bytes:
    """The CDR payload of a message, encapsulation header included."""
    writer = CdrWriter()
    _write_message(writer, message)
    return writer.getvalue()


def _read(reader: CdrReader, kind: str):
    if kind == "string":
        return reader.string()
    if kind in PRIMITIVES:
        return reader.primitive(kind)
    return _read_message(reader, TYPES[kind])


def _read_message(reader: CdrReader, cls: type[M]) -> M:
    values = {}
    for kind, name, array in fields(cls):
        if array is None:
            values[name] = _read(reader, kind)
            continue
        if array == 0 and kind == "uint8":
            values[name] = reader.blob()
            continue
        count = reader.count() if array == 0 else array
        if kind in PRIMITIVES and kind not in ("bool", "char", "byte"):
            values[name] = reader.primitives(kind, count)
        else:
            values[name] = [_read(reader, kind) for _ in range(count)]
    return cls.model_construct(**values)


def deserialize(cls: type[M], data: bytes | bytearray | memoryview) -> M:
    """Parse a CDR payload as ``cls``; raises :class:`CdrError` on any malformed input."""
    reader = CdrReader(data)
    try:
        message = _read_message(reader, cls)
    except (struct.error, OverflowError, ValueError) as exc:
        if isinstance(exc, CdrError):
            raise
        raise CdrError(f"{cls.ros_type}: {exc}") from None
    reader.done()
    return message


def message_definition(cls: type[RosMessage]) -> str:
    """The ``ros2msg`` schema of a type, then each type it uses after ``MSG:`` separators, as rosbag2 writes it."""
    order: list[type[RosMessage]] = []

    def visit(current: type[RosMessage]) -> None:
        for kind, _, _ in fields(current):
            if kind in TYPES and TYPES[kind] not in order:
                order.append(TYPES[kind])
                visit(TYPES[kind])

    visit(cls)
    parts = [cls.definition + "\n"]
    for dep in order:
        parts.append("=" * 80 + f"\nMSG: {dep.ros_type}\n{dep.definition}\n")
    return "".join(parts).replace("/msg/", "/")

