"""The recorder core: one MCAP file per session with every stream. Bytes in, file out.

Every twohr message is stored verbatim on ``/twohr/<robot>/<stream>`` (our own schema,
message encoding ``twohr``: exact replay). Alongside, Foxglove well-known channels make the
file viewable as is: CompressedImage (rgb, depth), ImageAnnotations (keypoints, boxes),
PoseInFrame and FrameTransform (``world`` -> ``<robot>/camera``).

Chunks are small and flushed to disk as they close, so a recorder that is killed leaves a
file whose written chunks are still readable (``read_messages`` recovers them).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from mcap.reader import NonSeekingReader
from mcap.writer import CompressionType, Writer

from twohr import keys
from twohr.messages import MESSAGE_TYPES, DynamicsMsg, FrameMsg, KeypointsMsg, PoseMsg, decode, split

from . import foxglove

WIRE_ENCODING = "twohr"


class SessionRecorder:
    """Writes one session's messages into ``path`` (an ``.mcap`` file)."""

    def __init__(self, path: str | Path, chunk_size: int = 256 * 1024) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.file = open(self.path, "wb")  # noqa: SIM115 (closed in close())
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

    def _foxglove(self, topic: str, schema: str, data: bytes, log_time: int) -> None:
        channel = self._channel(topic, schema, "jsonschema", foxglove.schema_bytes(schema), "json")
        self._add(channel, topic, data, log_time)

    def write(self, key: str, payload: bytes, log_time_ns: int | None = None) -> None:
        """Record one bus message; raises ``MessageError`` (and records nothing) if it is malformed."""
        robot, stream = keys.parse(key)
        message, parts = split(payload)
        log_time = log_time_ns if log_time_ns is not None else time.time_ns()
        cls = type(message)
        topic = f"/twohr/{robot}/{stream}"
        schema = json.dumps(cls.model_json_schema()).encode()
        self._add(self._channel(topic, cls.schema_name, "jsonschema", schema, WIRE_ENCODING), topic, payload, log_time)
        t = message.stamp
        if isinstance(message, FrameMsg):
            for spec, blob in parts:
                if spec.encoding in ("jpeg", "png"):
                    self._foxglove(f"/{robot}/camera/{spec.name}", "foxglove.CompressedImage",
                                   foxglove.compressed_image(t, f"{robot}/camera", blob, spec.encoding), log_time)
        elif isinstance(message, KeypointsMsg):
            _, arrays = decode(payload)
            self._foxglove(f"/{robot}/camera/keypoints", "foxglove.ImageAnnotations",
                           foxglove.keypoint_annotations(t, arrays["xy"]), log_time)
        elif isinstance(message, DynamicsMsg):
            _, arrays = decode(payload)
            self._foxglove(f"/{robot}/camera/dynamics", "foxglove.ImageAnnotations",
                           foxglove.box_annotations(t, arrays["boxes"]), log_time)
        elif isinstance(message, PoseMsg):
            self._foxglove(f"/{robot}/pose", "foxglove.PoseInFrame",
                           foxglove.pose_in_frame(t, message.position, message.orientation), log_time)
            self._foxglove("/tf", "foxglove.FrameTransform",
                           foxglove.frame_transform(t, "world", f"{robot}/camera", message.position,
                                                    message.orientation), log_time)
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


def known_schema(name: str) -> bool:
    return name in MESSAGE_TYPES or name in foxglove.SCHEMAS
