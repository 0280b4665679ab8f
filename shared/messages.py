"""Typed, versioned bus messages: a pydantic header plus a compact binary payload of arrays.

Wire format (little-endian)::

    b"2HR" | u8 wire version | u32 header length | header JSON (UTF-8) | array blobs, back to back

The header names the schema and lists each array's dtype, shape, encoding and byte length.
Images travel encoded (``jpeg``/``png``) or ``raw``; every other array is ``raw``. Every
message carries session id, robot id, frame index and timestamp. :func:`decode` validates
everything and raises :class:`MessageError` on any malformed payload, so a service can count
and drop it instead of crashing.
"""

from __future__ import annotations

import json
import math
import os
import struct
from typing import Annotated, Any, ClassVar, Literal

import cv2
import numpy as np
from pydantic import BaseModel, Field, ValidationError

from .config import PipelineConfig
from .dataset import CameraIntrinsics, Frame, depth_in_metres, undistorted
from .errors import TwohrError
from .features import Matches
from .ids import ID_PATTERN as ID_PATTERN
from .mapmodes import MapMode, MapRequest
from .trajectory import Trajectory

MAGIC = b"2HR"
WIRE_VERSION = 2  # 2: the control message says who started the session (started_by)
_PREFIX = struct.Struct("<3sBI")
_DTYPES = {"uint8", "uint16", "int32", "int64", "float32", "float64", "bool"}


#: The world frame of poses: the map's name in a session with a map, '' for the robot's own frame (its first camera).
FrameId = Annotated[str, Field(description="the world frame: the map's name in a session with a map, '' for the "
                                           "robot's own frame (its first camera)")]


class MessageError(TwohrError):
    """A payload that is not a valid twohr message."""


#: Largest dimension an array header may claim; beyond it numpy cannot even describe the array.
MAX_DIMENSION = 2**31 - 1
#: Most pixels an image in a message may have (a 640x480 camera sends 0.3 M, a 4K one 8.3 M): a larger claimed shape
#: is refused before decoding, and OpenCV refuses to decode a larger one (a PNG of a few bytes can claim gigapixels)
MAX_IMAGE_PIXELS = 100_000_000
os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", str(MAX_IMAGE_PIXELS))  # read at OpenCV's first decode


class ArraySpec(BaseModel):
    name: str = Field(max_length=64)
    dtype: str
    shape: list[Annotated[int, Field(ge=0, le=MAX_DIMENSION)]] = Field(max_length=8)
    encoding: Literal["raw", "jpeg", "png"] = "raw"
    nbytes: int = Field(ge=0)


class Message(BaseModel):
    """Fields every message carries. Subclasses add metadata fields and name their arrays."""

    schema_name: ClassVar[str] = "twohr.Message"
    required_arrays: ClassVar[tuple[str, ...]] = ()

    session_id: str = Field(pattern=ID_PATTERN)
    robot_id: str = Field(pattern=ID_PATTERN)
    frame_index: int = Field(ge=-1, description="-1 for messages about the session, not a frame")
    stamp: float = Field(description="sensor time of the frame, seconds")


class FrameMsg(Message):
    """An RGB-D frame: ``rgb`` (H, W, 3) uint8 RGB, ``depth`` (H, W) uint16 in ``camera.depth_factor`` units."""

    schema_name: ClassVar[str] = "twohr.Frame"
    required_arrays: ClassVar[tuple[str, ...]] = ("rgb", "depth")
    camera: CameraIntrinsics
    sent_at: float = Field(0.0, description="wall-clock time the source published it, for latency")


class ImageMsg(Message):
    """A frame's colour image alone, ``rgb`` (H, W, 3) uint8 RGB, for a stage that reads nothing else (the
    detector): the frame's header (its camera included) without the depth image."""

    schema_name: ClassVar[str] = "twohr.Image"
    required_arrays: ClassVar[tuple[str, ...]] = ("rgb",)
    camera: CameraIntrinsics
    sent_at: float = Field(0.0, description="wall-clock time the source published the frame, for latency")


class KeypointsMsg(Message):
    """Keypoints of a frame: ``xy``, ``descriptors``, ``scores`` (+ ``reliability``, ``repeatability``)."""

    schema_name: ClassVar[str] = "twohr.Keypoints"
    required_arrays: ClassVar[tuple[str, ...]] = ("xy", "descriptors", "scores")
    width: int
    height: int
    elapsed_ms: float = 0.0
    sent_at: float = 0.0


class DynamicsMsg(Message):
    """Dynamic-object detections and the mask of pixels to ignore: ``boxes``, ``scores``, ``class_ids``, ``mask``."""

    schema_name: ClassVar[str] = "twohr.Dynamics"
    required_arrays: ClassVar[tuple[str, ...]] = ("boxes", "scores", "class_ids", "mask")
    names: list[str] = Field(default_factory=list)
    levels: list[str] = Field(default_factory=list)
    elapsed_ms: float = 0.0
    sent_at: float = 0.0


class MatchesMsg(Message):
    """Correspondences between the frame's keypoints (A) and a reference set (B): ``idx_a``, ``idx_b``, ``scores``."""

    schema_name: ClassVar[str] = "twohr.Matches"
    required_arrays: ClassVar[tuple[str, ...]] = ("idx_a", "idx_b", "scores")
    reference: str = Field("", description="what B is, e.g. 'keyframe 12' or 'local map'")
    elapsed_ms: float = 0.0


class MatchRequestMsg(Message):
    """A matching query to the matcher service: descriptors ``desc_a`` and ``desc_b``. With ``desc_b_sizes`` (int64),
    ``desc_b`` holds several reference sets one after another, of those sizes, each matched to ``desc_a`` apart:
    the reply's ``set_counts`` says how many of its matches belong to each set, in order, and ``idx_b`` counts
    within its set (see :func:`split_matches`)."""

    schema_name: ClassVar[str] = "twohr.MatchRequest"
    required_arrays: ClassVar[tuple[str, ...]] = ("desc_a", "desc_b")
    reference: str = ""


def split_matches(matches: Matches, set_counts: np.ndarray | None) -> list[Matches]:
    """The matches of a reply, one :class:`~twohr.features.Matches` per reference set (``set_counts`` None: one)."""
    if set_counts is None:
        return [matches]
    bounds = np.cumsum(np.asarray(set_counts, np.int64))[:-1]
    return [Matches(a, b, s) for a, b, s in zip(np.split(matches.idx_a, bounds), np.split(matches.idx_b, bounds),
                                                 np.split(matches.scores, bounds), strict=True)]


def joined_matches(per_set: list[Matches]) -> dict[str, np.ndarray]:
    """The arrays of a reply to a query over several reference sets (the inverse of :func:`split_matches`)."""
    return {"idx_a": np.concatenate([m.idx_a for m in per_set]).astype("int64"),
            "idx_b": np.concatenate([m.idx_b for m in per_set]).astype("int64"),
            "scores": np.concatenate([m.scores for m in per_set]).astype("float32"),
            "set_counts": np.array([len(m) for m in per_set], np.int64)}


class PoseMsg(Message):
    """The tracker's camera-to-world pose of a frame, with tracking health."""

    schema_name: ClassVar[str] = "twohr.Pose"
    position: list[float] = Field(min_length=3, max_length=3)
    orientation: list[float] = Field(min_length=4, max_length=4, description="quaternion x, y, z, w")
    status: str
    num_keypoints: int = 0
    num_matches: int = 0
    num_inliers: int = 0
    is_keyframe: bool = False
    frame_sent_at: float = Field(0.0, description="when the source published the frame, for latency")
    elapsed_ms: dict[str, float] = Field(default_factory=dict)
    frame_id: FrameId = ""


class LandmarksMsg(Message):
    """The tracker's map points in world coordinates, published at keyframes: ``points`` (N, 3) float32."""

    schema_name: ClassVar[str] = "twohr.Landmarks"
    required_arrays: ClassVar[tuple[str, ...]] = ("points",)


class PathMsg(Message):
    """Corrected camera-to-world poses: ``stamps`` (N,) float64 and ``poses`` (N, 7) float64 rows of
    ``tx ty tz qx qy qz qw``. ``final`` False: a live correction, the keyframes' poses after bundle adjustment
    (a robot's earlier poses move with their keyframe); True: the refined trajectory of every frame, once the
    session has ended (final bundle adjustment, re-anchoring, smoothing; ``twohr run``'s ``trajectory.txt``).

    A live correction is ``full`` (every keyframe) or a delta: only the keyframes that are new or moved since the
    session's previous path message, so that messages stay small as a map grows; a full one comes every few
    messages and whenever keyframes went. :class:`PathAssembler` rebuilds the whole path from them."""

    schema_name: ClassVar[str] = "twohr.Path"
    required_arrays: ClassVar[tuple[str, ...]] = ("stamps", "poses")
    final: bool = False
    frame_id: FrameId = ""
    full: bool = Field(True, description="stamps and poses hold every keyframe (False: a delta)")
    seq: int = Field(0, ge=0, description="the session's path message number (a gap: a delta was lost)")
    keyframes: int = Field(0, ge=0, description="keyframes in the whole path once this message is applied")


class KeyframesMsg(Message):
    """A robot's keyframes for the map server, in a session that shares a map (``twohr/<robot>/keyframes``): the
    current pose of every keyframe so far, ``poses`` (K, 4, 4) float32 camera-to-world in the robot's own frame and
    ``stamps`` (K,) float64, and for the keyframes from ``first`` on, the keypoints that observe a described landmark:
    ``keypoint_first`` (n + 1,) int64 (where each new keyframe's begin), ``xy`` (P, 2) float32, ``depth`` (P,)
    float32 metres, ``landmark`` (P,) int64 and that landmark's position, ``positions`` (P, 3) float32; and the
    descriptors of the landmarks not sent before, ``described`` (M,) int64 ids and ``descriptors`` (M, D). The
    map server keeps what came, so each descriptor crosses the wire once."""

    schema_name: ClassVar[str] = "twohr.Keyframes"
    required_arrays: ClassVar[tuple[str, ...]] = ("poses", "stamps", "keypoint_first", "xy", "depth", "landmark",
                                                  "positions", "described", "descriptors")
    map_name: str = Field(description="the shared map the session builds")
    first: int = Field(ge=0, description="the index of the first keyframe whose keypoints this message carries")
    camera: CameraIntrinsics
    final: bool = Field(False, description="the session's last: its keyframes as the final bundle adjustment left them")


class MergeMsg(Message):
    """A robot placed in a shared map's frame (``twohr/maps/<name>/merged``): the map server found its keyframes in
    the map (``merged``), its session started the map (``defines``: its frame is the map's), or it localizes in the
    stored map (``joined``); ``refined``: a merged robot's transform moved, its later matches averaged in.
    ``position`` and ``orientation`` give the transform of the robot's own frame into the
    map's; from now on its poses carry frame ``map_name``. The header names the robot and its session; ``stamp`` is
    the stamp of the keyframe that completed the merge."""

    schema_name: ClassVar[str] = "twohr.Merge"
    map_name: str
    kind: Literal["defines", "joined", "merged", "refined"]
    position: list[float] = Field(min_length=3, max_length=3)
    orientation: list[float] = Field(min_length=4, max_length=4, description="quaternion x, y, z, w")
    into: list[str] = Field(default_factory=list, description="the robots whose keyframes it was found among")
    inliers: list[int] = Field(default_factory=list, description="the inliers of each agreeing match")
    keyframes: int = Field(0, ge=0, description="the robot's keyframes when it was merged")
    at: float = Field(description="wall-clock time of the event")
    ms: float = Field(0.0, ge=0, description="the map server's time for the search that merged it")

    @property
    def transform(self) -> np.ndarray:
        """(4, 4) the robot's own frame into the map's."""
        from .geometry import make_pose, quat_to_rot

        return make_pose(quat_to_rot(np.array(self.orientation)), np.array(self.position))


class StatusMsg(Message):
    """Session lifecycle and service health: ``state`` is started, running, finished, stopped or error."""

    schema_name: ClassVar[str] = "twohr.Status"
    service: str
    state: str
    detail: str = ""
    counters: dict[str, int] = Field(default_factory=dict)


class ControlMsg(Message):
    """Start, stop or move a session; ``config`` is the full validated pipeline configuration. ``move``: the
    session's tracker died, and ``tracker`` now serves it, from the robot's latest map snapshot (the other services
    go on as they were)."""

    schema_name: ClassVar[str] = "twohr.Control"
    command: Literal["start", "stop", "move"]
    sequence: str = ""
    rate: float = Field(0.0, ge=0, description="playback speed: 1 = real time, 0 = as fast as the pipeline keeps up")
    max_frames: int | None = Field(None, ge=1)
    record: bool = Field(True, description="write the session to MCAP")
    record_descriptors: bool = Field(False, description="also record the raw keypoint descriptors (large)")
    record_frames: bool = Field(False, description="also record the raw RGB-D frames verbatim, for exact replay")
    start: int = Field(0, ge=0, description="a replay's first frame")
    map_name: str = Field("", description="the map the session builds, localizes in or extends ('' = none)")
    map_mode: MapMode = Field(MapMode.NONE, description="what the session does with map_name ('' = none)")
    started_by: str = Field("", max_length=80, description="who started the session: the robot's id, or "
                            "'@operator' (the map room checks a save's rights and audits it with it)")
    config: PipelineConfig = Field(default_factory=PipelineConfig)
    tracker: str = Field("", description="the tracker replica that serves the session, as the gateway placed it "
                         "('' = every tracker that gets it: a stack with one)")

    @property
    def map_request(self) -> MapRequest | None:
        """The session's map as ``POST /sessions`` asked for it (None: it has none)."""
        return None if self.map_mode is MapMode.NONE else MapRequest(name=self.map_name, mode=self.map_mode)


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.schema_name: cls
    for cls in (FrameMsg, ImageMsg, KeypointsMsg, DynamicsMsg, MatchesMsg, MatchRequestMsg, PoseMsg, LandmarksMsg,
                PathMsg, StatusMsg, ControlMsg, KeyframesMsg, MergeMsg)
}


def _encode_array(name: str, array: np.ndarray, encoding: str) -> tuple[ArraySpec, bytes]:
    array = np.ascontiguousarray(array)
    if encoding == "raw":
        blob = array.tobytes()
    else:
        image = cv2.cvtColor(array, cv2.COLOR_RGB2BGR) if array.ndim == 3 else array
        params = [cv2.IMWRITE_JPEG_QUALITY, 95] if encoding == "jpeg" else [cv2.IMWRITE_PNG_COMPRESSION, 1]
        ok, buffer = cv2.imencode("." + ("jpg" if encoding == "jpeg" else "png"), image, params)
        if not ok:
            raise MessageError(f"cannot encode array {name} as {encoding}")
        blob = buffer.tobytes()
    return ArraySpec(name=name, dtype=str(array.dtype), shape=list(array.shape), encoding=encoding,
                     nbytes=len(blob)), blob


def encode(message: Message, arrays: dict[str, np.ndarray] | None = None,
           encodings: dict[str, str] | None = None, blobs: dict[str, tuple[ArraySpec, bytes]] | None = None) -> bytes:
    """Serialise a message and its arrays. ``encodings`` picks jpeg/png per array (default raw);
    ``blobs`` passes already-encoded images through untouched (e.g. the JPEG bytes of a file)."""
    specs, parts = [], []
    for name, array in (arrays or {}).items():
        spec, blob = _encode_array(name, array, (encodings or {}).get(name, "raw"))
        specs.append(spec)
        parts.append(blob)
    for spec, blob in (blobs or {}).values():
        specs.append(spec)
        parts.append(blob)
    header = {"schema": message.schema_name, "version": WIRE_VERSION, "body": message.model_dump(mode="json"),
              "arrays": [s.model_dump() for s in specs]}
    header_bytes = json.dumps(header, separators=(",", ":")).encode()
    return _PREFIX.pack(MAGIC, WIRE_VERSION, len(header_bytes)) + header_bytes + b"".join(parts)


def encoded_image(name: str, data: bytes, encoding: Literal["jpeg", "png"], dtype: str,
                  shape: tuple[int, ...]) -> tuple[ArraySpec, bytes]:
    """An already-encoded image blob for :func:`encode` (no re-encoding, so no extra loss)."""
    return ArraySpec(name=name, dtype=dtype, shape=list(shape), encoding=encoding, nbytes=len(data)), data


def _check_array(spec: ArraySpec) -> None:
    """What the header alone can tell: a known dtype and, for a raw array, a byte count that fits the shape."""
    if spec.dtype not in _DTYPES:
        raise MessageError(f"array {spec.name}: unsupported dtype {spec.dtype}")
    if spec.encoding == "raw":
        expected = math.prod(spec.shape) * np.dtype(spec.dtype).itemsize  # Python ints: no overflow
        if expected != spec.nbytes:
            raise MessageError(f"array {spec.name}: {spec.nbytes} bytes for shape {spec.shape} {spec.dtype}")
    elif math.prod(spec.shape[:2]) > MAX_IMAGE_PIXELS:
        raise MessageError(f"array {spec.name}: an image of {spec.shape[:2]} pixels, at most {MAX_IMAGE_PIXELS}")


def _imdecode(spec: ArraySpec, blob: bytes, flags: int) -> np.ndarray:
    """An encoded image blob, decoded; :class:`MessageError` when it is empty or not an image."""
    try:
        image = cv2.imdecode(np.frombuffer(blob, np.uint8), flags) if blob else None
    except cv2.error:
        image = None
    if image is None:
        raise MessageError(f"array {spec.name}: empty or corrupt {spec.encoding} data")
    return image


def decode_gray(spec: ArraySpec, blob: bytes) -> np.ndarray:
    """A colour image array of a payload (see :func:`split`) as a grayscale image, decoded straight to grey."""
    if spec.encoding == "raw":
        try:
            return cv2.cvtColor(decode_array(spec, blob), cv2.COLOR_RGB2GRAY)
        except cv2.error:
            raise MessageError(f"array {spec.name}: shape {spec.shape} {spec.dtype} is not an RGB image") from None
    image = _imdecode(spec, blob, cv2.IMREAD_GRAYSCALE)
    if list(image.shape) != spec.shape[:2]:
        raise MessageError(f"array {spec.name}: corrupt {spec.encoding} data or a shape other than {spec.shape}")
    return image


def decode_array(spec: ArraySpec, blob: bytes) -> np.ndarray:
    """One array of a payload (see :func:`split`), decoded."""
    if spec.encoding == "raw":
        try:
            return np.frombuffer(blob, dtype=spec.dtype).reshape(spec.shape)
        except ValueError as exc:  # e.g. a zero-size shape whose other dimensions numpy cannot address
            raise MessageError(f"array {spec.name}: shape {spec.shape}: {exc}") from None
    image = _imdecode(spec, blob, cv2.IMREAD_UNCHANGED)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    if list(image.shape) != spec.shape or str(image.dtype) != spec.dtype:
        raise MessageError(
            f"array {spec.name}: decoded {image.shape} {image.dtype}, header says {spec.shape} {spec.dtype}"
        )
    return image


def split(payload: bytes | bytearray | memoryview, expect: type[Message] | None = None
          ) -> tuple[Any, list[tuple[ArraySpec, bytes]]]:
    """Parse the header and cut out each array's blob, without decoding images.

    Raises :class:`MessageError` if anything is off."""
    payload = bytes(payload)
    if len(payload) < _PREFIX.size:
        raise MessageError(f"payload of {len(payload)} bytes is too short")
    magic, version, header_len = _PREFIX.unpack_from(payload)
    if magic != MAGIC:
        raise MessageError("not a twohr message (bad magic)")
    if version != WIRE_VERSION:
        raise MessageError(f"wire version {version} is not supported (this build speaks {WIRE_VERSION})")
    end = _PREFIX.size + header_len
    if end > len(payload):
        raise MessageError("truncated header")
    try:
        header = json.loads(payload[_PREFIX.size:end])
        cls = MESSAGE_TYPES[header["schema"]]
        message = cls.model_validate(header["body"])
        specs = [ArraySpec.model_validate(s) for s in header["arrays"]]
    except (ValueError, KeyError, TypeError, ValidationError, RecursionError) as exc:  # RecursionError: deep JSON
        raise MessageError(f"malformed header: {(str(exc).splitlines() or [type(exc).__name__])[0]}") from None
    if expect is not None and cls is not expect:
        raise MessageError(f"expected {expect.schema_name}, got {cls.schema_name}")
    parts, offset = [], end
    for spec in specs:
        _check_array(spec)
        blob = payload[offset: offset + spec.nbytes]
        if len(blob) != spec.nbytes:
            raise MessageError(f"array {spec.name}: truncated payload")
        parts.append((spec, blob))
        offset += spec.nbytes
    if offset != len(payload):
        raise MessageError(f"{len(payload) - offset} trailing bytes")
    missing = [name for name in cls.required_arrays if name not in {spec.name for spec, _ in parts}]
    if missing:
        raise MessageError(f"{cls.schema_name} lacks arrays {missing}")
    return message, parts


def decode(payload: bytes | bytearray | memoryview, expect: type[Message] | None = None,
           only: tuple[str, ...] | None = None) -> tuple[Any, dict]:
    """Parse a payload into ``(message, arrays)``, decoding only the arrays named in ``only`` if given.

    Raises :class:`MessageError` if anything is off."""
    message, parts = split(payload, expect)
    return message, {spec.name: decode_array(spec, blob) for spec, blob in parts if only is None or spec.name in only}


def relayed_frame(payload: bytes, session_id: str, frame_index: int) -> bytes:
    """A camera's frame message (``twohr/<robot>/camera``) as a session's frame (``frames``): the session's id and
    frame number in its header, the camera's send time kept (now where it gave none). The encoded images go on as
    they came: no decoding, no re-encoding. :class:`MessageError` for a malformed message."""
    import time

    frame, parts = split(payload, FrameMsg)
    relayed = frame.model_copy(update={"session_id": session_id, "frame_index": frame_index,
                                       "sent_at": frame.sent_at or time.time()})
    return encode(relayed, blobs={spec.name: (spec, blob) for spec, blob in parts})


def colour_image(payload: bytes) -> bytes:
    """A frame message as an :class:`ImageMsg`: the colour image as it came (a stage that reads nothing else gets
    no depth over the wire, half the frame's bytes)."""
    frame, parts = split(payload, FrameMsg)
    return encode(ImageMsg(**frame.model_dump()), blobs={spec.name: (spec, blob) for spec, blob in parts
                                                         if spec.name == "rgb"})


def received_frame(payload: bytes) -> tuple[FrameMsg, Frame]:
    """A frame message as its header and a :class:`~twohr.dataset.Frame` that keeps the message and decodes each
    image (undistorted; depth in metres) on first use. Raises :class:`MessageError` for a malformed message;
    a corrupt image raises it when that image is first read."""
    header, parts = split(payload, FrameMsg)
    images = {spec.name: (spec, blob) for spec, blob in parts}
    camera = header.camera
    decoders = {"rgb": lambda: undistorted(decode_array(*images["rgb"]), camera),
                "gray": lambda: undistorted(decode_gray(*images["rgb"]), camera),
                "depth": lambda: depth_in_metres(decode_array(*images["depth"]), camera)}
    return header, Frame(header.frame_index, header.stamp, message=bytes(payload), decoders=decoders)


def path_arrays(trajectory: Trajectory) -> dict[str, np.ndarray]:
    """The arrays of a :class:`PathMsg` for a trajectory."""
    rows = trajectory.to_tum_array() if len(trajectory) else np.zeros((0, 8))
    return {"stamps": np.asarray(trajectory.stamps, np.float64), "poses": np.ascontiguousarray(rows[:, 1:])}


def path_trajectory(arrays: dict[str, np.ndarray]) -> Trajectory:
    """The trajectory of a decoded :class:`PathMsg`; :class:`MessageError` when its arrays do not fit."""
    stamps, rows = np.asarray(arrays["stamps"], np.float64), np.asarray(arrays["poses"], np.float64)
    if stamps.ndim != 1 or rows.shape != (len(stamps), 7) or not np.isfinite(rows).all() or (
            len(rows) and np.linalg.norm(rows[:, 3:], axis=1).min() < 1e-9):
        raise MessageError(f"a path needs stamps (N,) and finite poses (N, 7) with unit quaternions, got "
                           f"{stamps.shape} and {rows.shape}")
    return Trajectory.from_tum_array(np.column_stack([stamps, rows]))


#: a keyframe's pose that moved less than this (metres, or quaternion components) since it was sent is not sent again
PATH_TOLERANCE = 1e-5


class PathDeltas:
    """The sender's side of live corrections: each call gives the next :class:`PathMsg` fields and arrays for a
    session's keyframe path, a delta (new and moved keyframes) or, every ``full_every`` messages and whenever a
    keyframe went, the full path."""

    def __init__(self, full_every: int = 10) -> None:
        self.full_every = full_every
        self.sent: dict[float, np.ndarray] = {}  # stamp -> the row last sent
        self.seq = -1

    def next(self, keyframes: Trajectory) -> tuple[dict, dict[str, np.ndarray]]:
        """(``full``, ``seq``, ``keyframes`` fields; the ``stamps`` and ``poses`` arrays) of the next message."""
        arrays = path_arrays(keyframes)
        stamps, rows = arrays["stamps"], arrays["poses"]
        self.seq += 1
        full = self.seq % self.full_every == 0 or not set(self.sent) <= set(stamps.tolist())
        if not full:
            changed = [i for i, (stamp, row) in enumerate(zip(stamps.tolist(), rows, strict=True))
                       if stamp not in self.sent or np.abs(self.sent[stamp] - row).max() > PATH_TOLERANCE]
            arrays = {"stamps": stamps[changed], "poses": np.ascontiguousarray(rows[changed])}
        self.sent = dict(zip(stamps.tolist(), rows, strict=True))
        return {"full": full, "seq": self.seq, "keyframes": len(stamps)}, arrays


class PathAssembler:
    """The receiver's side: each session's whole keyframe path, rebuilt from its full and delta :class:`PathMsg`
    messages. After a lost message (a gap in ``seq``) the path is unknown until the next full one."""

    def __init__(self, keep: int = 64) -> None:
        self.keep = keep
        self.paths: dict[str, tuple[int, dict[float, np.ndarray]] | None] = {}

    def add(self, message: PathMsg, arrays: dict[str, np.ndarray]) -> Trajectory | None:
        """The session's whole path after ``message`` (its trajectory as sent, for a final or full one), or None
        while it is unknown. Raises :class:`MessageError` for arrays that are no path."""
        trajectory = path_trajectory(arrays)
        if message.final or message.full:
            self._keep(message.session_id, (message.seq, dict(zip(trajectory.stamps.tolist(), arrays["poses"],
                                                                   strict=True))))
            return trajectory
        known = self.paths.get(message.session_id)
        if known is None or known[0] + 1 != message.seq:
            self.paths[message.session_id] = None
            return None
        rows = known[1] | dict(zip(trajectory.stamps.tolist(), arrays["poses"], strict=True))
        if len(rows) != message.keyframes:
            self.paths[message.session_id] = None
            return None
        self.paths[message.session_id] = (message.seq, rows)
        stamps = sorted(rows)
        return path_trajectory({"stamps": np.array(stamps), "poses": np.array([rows[s] for s in stamps])})

    def _keep(self, session_id: str, state) -> None:
        self.paths.pop(session_id, None)
        self.paths[session_id] = state
        while len(self.paths) > self.keep:  # the oldest sessions go
            self.paths.pop(next(iter(self.paths)))


def pose_trajectory(poses: list[PoseMsg]) -> Trajectory:
    """Pose messages as a camera-to-world trajectory, ordered by frame index; raises :class:`MessageError` for a
    pose with a zero or non-finite quaternion or position (it is no pose)."""
    ordered = sorted(poses, key=lambda p: p.frame_index)
    values = np.array([[*p.orientation, *p.position] for p in ordered]).reshape(-1, 7)
    broken = [p.frame_index for p, row in zip(ordered, values, strict=True)
              if not (np.isfinite(row).all() and np.linalg.norm(row[:4]) > 1e-9)]
    if broken:
        raise MessageError(f"the poses of frames {broken[:5]} have a zero or non-finite orientation or position")
    stamps = np.array([p.stamp for p in ordered], np.float64)
    return Trajectory.from_tum_array(np.column_stack([stamps, values[:, 4:], values[:, :4]]))
