"""MCAP files that survive a crash: is a file finalised, and re-indexing the readable prefix of one that is not.

A recording whose writer died has no summary or footer, so the standard readers refuse it. Its records
up to the cut are intact, though: :func:`recover` streams them out (unordered, stopping at the torn tail)
into a complete, indexed file and leaves ``<name>.partial.json`` beside it to say so.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

from mcap.reader import NonSeekingReader
from mcap.writer import CompressionType, Writer

from .files import replacing
from .paths import open_private

MCAP_MAGIC = b"\x89MCAP0\r\n"


def is_finalised(path: str | Path) -> bool:
    """True once an MCAP file ends with its closing magic (its writer wrote the summary and footer)."""
    try:
        with open(path, "rb") as fh:
            fh.seek(-len(MCAP_MAGIC), os.SEEK_END)
            return fh.read() == MCAP_MAGIC
    except OSError:
        return False


def partial_marker(path: str | Path) -> Path:
    """The file that marks a recording as recovered from a crash."""
    return Path(path).with_suffix(".partial.json")


def recover(path: str | Path) -> int | None:
    """Rewrite an unfinalised MCAP file as a complete one holding every message of its readable prefix, and
    write :func:`partial_marker` beside it. Returns the messages kept, or None if the file was complete."""
    path = Path(path)
    if is_finalised(path):
        return None
    kept = 0
    with replacing(path) as dst, open(path, "rb") as src:
        writer = Writer(dst, compression=CompressionType.ZSTD)
        writer.start(profile="", library="twohr (recovered)")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        try:
            for schema, channel, message in NonSeekingReader(src, validate_crcs=True).iter_messages(
                    log_time_order=False):
                if schema is not None and schema.id not in schemas:
                    schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
                if channel.id not in channels:
                    channels[channel.id] = writer.register_channel(
                        channel.topic, channel.message_encoding, schemas.get(channel.schema_id, 0), channel.metadata)
                writer.add_message(channels[channel.id], log_time=message.log_time, data=message.data,
                                   publish_time=message.publish_time, sequence=message.sequence)
                kept += 1
        except Exception:  # noqa: BLE001 - the torn tail ends the readable part, by design
            pass
        writer.finish()
    with open_private(partial_marker(path), "w") as marker:
        marker.write(json.dumps({"messages": kept, "recovered_at": time.time()}))
    return kept
