"""The source core: a TUM-layout sequence turned into frame messages. Files in, payloads out.

Colour and depth travel as the files' own encoded bytes (JPEG/PNG), validated by decoding
once, so every consumer decodes exactly the pixels that ``twohr run`` reads from disk.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from twohr.dataset import RGBDSequence
from twohr.errors import DatasetError
from twohr.messages import FrameMsg, encode, encoded_image

log = logging.getLogger(__name__)


def _encoding_of(path) -> str:
    return "png" if path.suffix.lower() == ".png" else "jpeg"


@dataclass
class PlaybackItem:
    index: int
    stamp: float
    payload: bytes


def frame_payloads(sequence: RGBDSequence, session_id: str, robot_id: str, start: int = 0,
                   max_frames: int | None = None, pace: Callable[[float], None] | None = None,
                   stamp_offset: float = 0.0) -> Iterator[PlaybackItem]:
    """Encoded :class:`FrameMsg` payloads of a sequence; corrupt frames are skipped, logged and counted
    in ``sequence.skipped``. ``pace(stamp)`` is called before each frame is stamped with its send time.
    ``stamp_offset`` is added to every stamp (a sequence played again in a loop goes on in time)."""
    stop = len(sequence) if max_frames is None else min(len(sequence), start + max_frames)
    for index in range(start, stop):
        record = sequence.records[index]
        try:
            height, width = sequence.check(index)  # both images' headers: the consumers decode the pixels
        except DatasetError as exc:
            log.warning("skipping frame %d: %s", index, exc)
            sequence.skipped.append(index)
            continue
        stamp = record.stamp + stamp_offset
        if pace is not None:
            pace(stamp)
        message = FrameMsg(session_id=session_id, robot_id=robot_id, frame_index=index, stamp=stamp,
                           camera=sequence.camera, sent_at=time.time())
        blobs = {
            "rgb": encoded_image("rgb", record.rgb_path.read_bytes(), _encoding_of(record.rgb_path), "uint8",
                                 (height, width, 3)),
            "depth": encoded_image("depth", record.depth_path.read_bytes(), "png", "uint16", (height, width)),
        }
        yield PlaybackItem(index, stamp, encode(message, blobs=blobs))
