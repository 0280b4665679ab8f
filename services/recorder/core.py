"""The recorder core: one MCAP file per session, lean enough to keep (about 50 kB per frame). Bytes in, file out.

Two kinds of channels:

* **Foxglove channels** (foxglove-sdk's typed schemas, protobuf; :mod:`twohr.foxglove_convert`): the colour
  image once, as JPEG (``CompressedImage``), the ``CameraCalibration``, keypoint and dynamic-mask annotations
  (``ImageAnnotations``), the pose (``PoseInFrame``), the path (``PosesInFrame``), the map points
  (``PointCloud``) and ``/tf`` (``FrameTransforms``): the file opens in Foxglove as it is.
* **twohr channels** ``/twohr/<robot>/<stream>`` (our own schema, message encoding ``twohr``): every message
  verbatim except the two large ones. Raw RGB-D frames are left out (the image is on the Foxglove channel)
  unless ``record_frames``; keypoint descriptors are emptied (shape (N, 0)) unless ``record_descriptors``.
  The poses are always there, so ``twohr eval --est FILE.mcap`` scores a recording.

Chunks are small and flushed to disk as they close, so a recorder that is killed leaves a
file whose written chunks are still readable (``read_messages`` recovers them).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from mcap.reader import NonSeekingReader
from mcap.writer import CompressionType, Writer
from pydantic import BaseModel, Field

from twohr import keys
from twohr.errors import TwohrError
from twohr.foxglove_convert import FoxgloveConverter
from twohr.messages import (
    FrameMsg,
    KeypointsMsg,
    PathMsg,
    PoseMsg,
    decode,
    encode,
    path_trajectory,
    pose_trajectory,
    split,
)
from twohr.paths import open_private
from twohr.trajectory import Trajectory

WIRE_ENCODING = "twohr"


class RecordingOptions(BaseModel):
    """What a recording keeps beyond the standard channels."""

    record_descriptors: bool = Field(False, description="keep the raw keypoint descriptors (about 0.5 MB/keyframe)")
    record_frames: bool = Field(False, description="keep the raw RGB-D frames verbatim (about 180 kB/frame)")
    jpeg_quality: int = Field(80, ge=10, le=100, description="JPEG quality of the recorded colour image")
    path_every: int = Field(10, ge=1, description="record the path (all poses so far) with every n-th pose")


class SessionRecorder:
    """Writes one session's messages into ``path`` (an ``.mcap`` file)."""

    def __init__(self, path: str | Path, options: RecordingOptions | None = None,
                 chunk_size: int = 256 * 1024) -> None:
        self.path = Path(path)
        self.options = options or RecordingOptions()
        self.converter = FoxgloveConverter(self.options.jpeg_quality, self.options.path_every)
        self.path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        self.file = open_private(self.path)  # closed in close(); 0600: the robots' surroundings are no one else's
        self.writer = Writer(self.file, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self.writer.start(profile="", library="twohr")
        self.schemas: dict[str, int] = {}
        self.channels: dict[str, int] = {}
        self.counts: dict[str, int] = {}
        self.closed = False

    def _channel(self, topic: str, schema_name: str, schema_encoding: str, schema_data: bytes, encoding: str) -> int:
        if topic not in self.channels:
            if schema_name not in self.schemas:
                self.schemas[schema_name] = self.writer.register_schema(schema_name, schema_encoding, schema_data)
            self.channels[topic] = self.writer.register_channel(topic, encoding, self.schemas[schema_name])
        return self.channels[topic]

    def _add(self, channel: int, topic: str, data: bytes, log_time: int) -> None:
        self.counts[topic] = self.counts.get(topic, 0) + 1
        self.writer.add_message(channel, log_time=log_time, data=data, publish_time=log_time,
                                sequence=self.counts[topic])

    def _foxglove(self, topic: str, message, log_time: int) -> None:
        schema = message.get_schema()
        channel = self._channel(topic, schema.name, schema.encoding, schema.data, schema.encoding)
        self._add(channel, topic, message.encode(), log_time)

    def _verbatim(self, message, payload: bytes) -> bytes | None:
        """The twohr payload to keep for a bus message (None: leave it out)."""
        if isinstance(message, FrameMsg) and not self.options.record_frames:
            return None
        if isinstance(message, KeypointsMsg) and not self.options.record_descriptors:
            _, arrays = decode(payload)
            arrays["descriptors"] = np.zeros((len(arrays["xy"]), 0), np.float32)
            return encode(message, arrays)
        return payload

    def write(self, key: str, payload: bytes, log_time_ns: int | None = None) -> None:
        """Record one bus message; raises ``MessageError`` (and records nothing) if it is malformed."""
        robot, stream = keys.parse(key)
        message, _ = split(payload)
        log_time = log_time_ns if log_time_ns is not None else time.time_ns()
        try:
            converted = self.converter.convert(payload)
        except ValueError:  # a corrupt image inside a well-formed message: keep the rest
            converted = []
            self.counts["unconvertible"] = self.counts.get("unconvertible", 0) + 1
        kept = self._verbatim(message, payload)
        if kept is not None:
            cls = type(message)
            topic = f"/twohr/{robot}/{stream}"
            schema = json.dumps(cls.model_json_schema()).encode()
            self._add(self._channel(topic, cls.schema_name, "jsonschema", schema, WIRE_ENCODING), topic, kept,
                      log_time)
        for topic, fox in converted:
            self._foxglove(topic, fox, log_time)
        self.file.flush()

    def close(self) -> None:
        """Write the summary and footer; the file is then a complete, indexed MCAP."""
        if not self.closed:
            self.writer.finish()
            self.file.close()
            self.closed = True


def read_messages(path: str | Path) -> list[tuple[str, bytes, int]]:
    """All messages of a recording as (topic, data, log_time), also from a file cut short by a kill."""
    out = []
    with open(path, "rb") as fh:
        reader = NonSeekingReader(fh, validate_crcs=True)
        try:
            for _schema, channel, message in reader.iter_messages(log_time_order=False):
                out.append((channel.topic, message.data, message.log_time))
        except Exception:  # noqa: BLE001 - a truncated tail ends the readable part, by design
            pass
    return out


def topic_counts(path: str | Path) -> dict[str, int]:
    """Message count per topic."""
    counts: dict[str, int] = {}
    for topic, _, _ in read_messages(path):
        counts[topic] = counts.get(topic, 0) + 1
    return counts


def recorded_trajectory(path: str | Path, robot_id: str | None = None, online: bool = False) -> Trajectory:
    """A recording's trajectory, camera-to-world: the refined one the tracker sent when the session ended (its final
    ``twohr.Path``) where the file has it and ``online`` is False, else the poses as published (its ``twohr.Pose``
    messages, ordered by frame). ``robot_id`` picks one robot where a file holds several."""
    poses: dict[str, list[PoseMsg]] = {}
    refined: dict[str, Trajectory] = {}
    for topic, data, _ in read_messages(path):
        if topic.startswith("/twohr/") and topic.endswith("/pose"):
            pose, _ = decode(data, PoseMsg)
            poses.setdefault(pose.robot_id, []).append(pose)
        elif topic.startswith("/twohr/") and topic.endswith("/path") and not online:
            message, arrays = decode(data, PathMsg)
            if message.final:
                refined[message.robot_id] = path_trajectory(arrays)
    if robot_id is not None:
        poses = {robot_id: poses.get(robot_id, [])}
    if len(poses) != 1 or not next(iter(poses.values())):
        found = ", ".join(sorted(poses)) or "none"
        raise TwohrError(f"{path}: need the poses of exactly one robot (found: {found}); pick one with --robot")
    robot, robot_poses = next(iter(poses.items()))
    return refined[robot] if robot in refined else pose_trajectory(robot_poses)
