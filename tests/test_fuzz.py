"""Fuzzing: malformed bytes into :func:`twohr.messages.decode` (hypothesis), malformed payloads on every key each
role may publish on the secured stack that ``twohr up`` starts, and a 10 s flood from an outside client.
Real router, real processes, real frames."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from twohr.dataset import CAMERA_PRESETS
from twohr.messages import (
    ControlMsg,
    FrameMsg,
    KeypointsMsg,
    MessageError,
    PoseMsg,
    StatusMsg,
    decode,
    encode,
    split,
)

IDS = {"session_id": "s1", "robot_id": "r1", "frame_index": 3, "stamp": 12.5}
FUZZ = settings(max_examples=400, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])


def valid_payloads() -> list[bytes]:
    """One payload of each kind of content: encoded images, raw arrays, nested config, plain metadata."""
    rng = np.random.default_rng(0)
    camera = CAMERA_PRESETS["bonn"].model_copy(update={"width": 32, "height": 24})
    rgb = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
    depth = rng.integers(0, 5000, (24, 32), dtype=np.uint16)
    return [
        encode(FrameMsg(**IDS, camera=camera), {"rgb": rgb, "depth": depth}, {"rgb": "jpeg", "depth": "png"}),
        encode(KeypointsMsg(**IDS, width=32, height=24),
               {"xy": rng.random((5, 2), dtype=np.float32), "descriptors": rng.random((5, 8), dtype=np.float32),
                "scores": rng.random(5, dtype=np.float32)}),
        encode(PoseMsg(**IDS, position=[1, 2, 3], orientation=[0, 0, 0, 1], status="tracking")),
        encode(ControlMsg(**IDS, command="start", sequence="seq", max_frames=10)),
        encode(StatusMsg(**IDS, service="source", state="running", counters={"frames": 3})),
    ]


VALID = valid_payloads()


def parts(payload: bytes) -> tuple[dict, bytes]:
    (header_len,) = struct.unpack_from("<I", payload, 4)
    return json.loads(payload[8:8 + header_len]), payload[8 + header_len:]


def assemble(header: dict | bytes, blobs: bytes) -> bytes:
    raw = header if isinstance(header, bytes) else json.dumps(header).encode()
    return b"2HR\x01" + struct.pack("<I", len(raw)) + raw + blobs


def only_message_errors(payload: bytes) -> None:
    """decode and split either succeed or raise MessageError, nothing else."""
    for parse in (split, decode):
        try:
            parse(payload)
        except MessageError:
            pass


json_values = st.recursive(
    st.none() | st.booleans() | st.integers(min_value=-(2**70), max_value=2**70) | st.floats() | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12)
dimensions = st.integers(-3, 64) | st.sampled_from([2**31 - 1, 2**31, 2**32, 2**40, 2**63 - 1, 2**63, 2**64, 2**100,
                                                     -(2**63)])
dtypes = st.sampled_from(["uint8", "uint16", "int32", "int64", "float32", "float64", "bool", "float16", "object",
                          "<f4", ">u2", "U10", "S3", "V8", "complex128", "", "int", 7, None])


@FUZZ
@given(st.binary(max_size=4096))
def test_random_bytes_raise_only_message_errors(payload):
    only_message_errors(payload)
    only_message_errors(b"2HR\x01" + payload)


@FUZZ
@given(st.sampled_from(VALID), st.data())
def test_mutated_header_fields_raise_only_message_errors(payload, data):
    """Replace any one value anywhere in the header JSON (body fields, array specs, schema, version)."""
    header, blobs = parts(payload)
    paths, stack = [], [((), header)]
    while stack:
        path, node = stack.pop()
        children = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
        for key, child in children:
            paths.append(path + (key,))
            stack.append((path + (key,), child))
    path = data.draw(st.sampled_from(paths))
    target = header
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = data.draw(json_values)
    only_message_errors(assemble(header, blobs))


@FUZZ
@given(st.sampled_from([p for p in VALID if parts(p)[0]["arrays"]]), st.data())
def test_mutated_array_specs_raise_only_message_errors(payload, data):
    """Shapes (huge, negative, too many dims), dtypes, encodings and byte counts that lie about the blobs."""
    header, blobs = parts(payload)
    spec = data.draw(st.sampled_from(header["arrays"]))
    field = data.draw(st.sampled_from(["shape", "dtype", "nbytes", "encoding", "all"]))
    if field in ("shape", "all"):
        spec["shape"] = data.draw(st.lists(dimensions, max_size=10))
    if field in ("dtype", "all"):
        spec["dtype"] = data.draw(dtypes)
    if field in ("nbytes", "all"):
        spec["nbytes"] = data.draw(st.integers(-10, len(blobs) + 10) | st.sampled_from([2**63, 2**64, -(2**64)]))
    if field in ("encoding", "all"):
        spec["encoding"] = data.draw(st.sampled_from(["raw", "jpeg", "png", "gif", ""]))
    only_message_errors(assemble(header, blobs))


@FUZZ
@given(st.sampled_from(VALID), st.data())
def test_truncated_extended_and_flipped_payloads_raise_only_message_errors(payload, data):
    kind = data.draw(st.sampled_from(["truncate", "trail", "flip", "length"]))
    if kind == "truncate":
        payload = payload[:data.draw(st.integers(0, len(payload) - 1))]
    elif kind == "trail":
        payload = payload + data.draw(st.binary(min_size=1, max_size=64))
    elif kind == "flip":
        mutable = bytearray(payload)
        for _ in range(data.draw(st.integers(1, 8))):
            mutable[data.draw(st.integers(0, len(mutable) - 1))] = data.draw(st.integers(0, 255))
        payload = bytes(mutable)
    else:
        payload = payload[:4] + struct.pack("<I", data.draw(st.integers(0, 2**32 - 1))) + payload[8:]
    only_message_errors(payload)


@FUZZ
@given(st.sampled_from(["twohr.Landmarks", "twohr.Frame", "twohr.Pose"]), st.data())
def test_generated_array_specs_raise_only_message_errors(schema, data):
    """Headers whose array specs are drawn whole, each followed by exactly as many bytes as it claims."""
    specs, blobs = [], b""
    for name in data.draw(st.lists(st.sampled_from(["points", "rgb", "depth", "x"]), max_size=3)):
        shape = data.draw(st.lists(dimensions, max_size=9))
        dtype = data.draw(dtypes)
        encoding = data.draw(st.sampled_from(["raw", "jpeg", "png"]))
        blob = data.draw(st.binary(max_size=64))
        if encoding == "raw" and dtype in ("uint8", "uint16", "float32") and all(0 <= d < 16 for d in shape):
            blob = bytes(int(np.prod(shape)) * np.dtype(dtype).itemsize)  # a raw blob that fits its shape
        specs.append({"name": name, "dtype": dtype, "shape": shape, "encoding": encoding, "nbytes": len(blob)})
        blobs += blob
    body = {**IDS, "position": [0, 0, 0], "orientation": [0, 0, 0, 1], "status": "x",
            "camera": CAMERA_PRESETS["bonn"].model_dump()}
    only_message_errors(assemble({"schema": schema, "version": 1, "body": body, "arrays": specs}, blobs))


@FUZZ
@given(st.integers(0, 5000), st.sampled_from([b"[", b'{"a":', b'{"schema":[']))
def test_deeply_nested_headers_raise_only_message_errors(depth, opener):
    closer = {b"[": b"]", b'{"a":': b"}", b'{"schema":[': b"]}"}[opener]
    only_message_errors(assemble(opener * depth + b"0" + closer * depth, b""))


@pytest.mark.parametrize("header", [
    b"[" * 100_000 + b"]" * 100_000,  # JSON nested past the parser's recursion limit
    json.dumps({"schema": "twohr.Landmarks", "body": IDS,
                "arrays": [{"name": "points", "dtype": "float32", "shape": [0, 2**62], "nbytes": 0}]}).encode(),
    json.dumps({"schema": "twohr.Landmarks", "body": IDS,
                "arrays": [{"name": "points", "dtype": "uint8", "shape": [1], "encoding": "jpeg", "nbytes": 0}]
                }).encode(),
], ids=["deep-json", "dimension-overflow", "empty-jpeg"])
def test_what_the_fuzzer_found_is_a_message_error(header):
    with pytest.raises(MessageError):
        decode(assemble(header, b""))


def test_valid_payloads_still_decode():
    for payload in VALID:
        message, arrays = decode(payload)
        assert message.frame_index == 3 and all(a.size for a in arrays.values())
