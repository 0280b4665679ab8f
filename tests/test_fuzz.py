"""Fuzzing: malformed bytes into :func:`twohr.messages.decode` (hypothesis), malformed payloads on every key each
role may publish on the secured stack that ``twohr up`` starts, and a 10 s flood from an outside client.
Real router, real processes, real frames."""

from __future__ import annotations

import json
import struct
import time
from collections import Counter

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
    decode_gray,
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
    """decode and split (and decode_gray on each array the tracker might take for a colour image) either succeed
    or raise MessageError, nothing else."""
    for parse in (split, decode):
        try:
            parse(payload)
        except MessageError:
            pass
    try:
        _, arrays = split(payload)
    except MessageError:
        return
    for spec, blob in arrays:
        try:
            decode_gray(spec, blob)
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


# -- the bus: malformed payloads on every key each role may publish, and a flood from an outside client --------

ROBOT = "fuzzbot"


@pytest.fixture(scope="module")
def stack(tmp_path_factory, dev_sequence):
    from twohr.bus import free_port
    from twohr_app.supervisor import start_system

    recordings = tmp_path_factory.mktemp("recordings")
    system = start_system(f"tcp/127.0.0.1:{free_port()}", [str(dev_sequence.parent)], str(recordings), "127.0.0.1",
                          free_port(), api_token="fuzz-token-0123456789", timeout=180,
                          maps=str(tmp_path_factory.mktemp("maps")))
    yield {"system": system, "recordings": recordings}
    system.stop()


def dev_frame(dev_sequence, robot: str, session_id: str, index: int = 0) -> bytes:
    """A real dev frame as a camera driver sends it: the JPEG and PNG bytes from disk."""
    from twohr.dataset import RGBDSequence
    from twohr.messages import encoded_image

    sequence = RGBDSequence(dev_sequence)
    record = sequence.records[index]
    shape = (sequence.camera.height, sequence.camera.width)
    return encode(FrameMsg(session_id=session_id, robot_id=robot, frame_index=index, stamp=record.stamp,
                           camera=sequence.camera),
                  blobs={"rgb": encoded_image("rgb", record.rgb_path.read_bytes(), "jpeg", "uint8", (*shape, 3)),
                         "depth": encoded_image("depth", record.depth_path.read_bytes(), "png", "uint16", shape)})


def malformed_payloads(frame: bytes) -> list[bytes]:
    """Payloads no service may choke on; ``frame`` is a valid frame message of robot ROBOT."""
    header, blobs = parts(frame)
    rgb_spec, depth_spec = header["arrays"]
    rgb_len = rgb_spec["nbytes"]

    def variant(arrays=None, body=None, schema=None, tail=None) -> bytes:
        changed = {**header, "arrays": arrays or header["arrays"], "body": {**header["body"], **(body or {})},
                   "schema": schema or header["schema"]}
        return assemble(changed, blobs if tail is None else tail)

    rng = np.random.default_rng(7)
    return [
        b"", b"2HR", rng.bytes(64), rng.bytes(65536), b"2HR\x01" + struct.pack("<I", 10**6) + b"{}",
        assemble(b"[" * 5000 + b"]" * 5000, b""),
        frame[: len(frame) // 2], frame + b"trailing",
        variant(body={"robot_id": "someone_else"}),  # a frame for another robot than the key's
        variant(body={"session_id": "../../etc"}),
        variant(body={"camera": {"fx": -1}}),
        variant(schema="twohr.Control"),  # a frame's body as a control message
        variant(arrays=[{**rgb_spec, "shape": [48000, 64000, 3]}, depth_spec]),  # a shape the JPEG is not
        variant(arrays=[{**rgb_spec, "shape": [0, 2**31 - 1, 2**31 - 1]}, depth_spec]),
        variant(tail=rng.bytes(rgb_len) + blobs[rgb_len:]),  # noise where the JPEG should be
        variant(arrays=[{**rgb_spec, "encoding": "raw"}, depth_spec]),
        encode(ControlMsg(session_id="nosuchsession", robot_id=ROBOT, frame_index=-1, stamp=0.0, command="stop")),
        encode(StatusMsg(session_id="nosuchsession", robot_id=ROBOT, frame_index=-1, stamp=0.0, service="source",
                         state="error", detail="fuzz")),
        frame,  # well formed, for a session nobody started
    ]


def rss_mb(pid: int) -> float:
    for line in open(f"/proc/{pid}/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError(f"no VmRSS for {pid}")


def health_of_all(system) -> dict[str, dict | None]:
    from twohr.bus import open_session, query_health
    from twohr.keys import PIPELINE_SERVICES

    session = open_session(system.bus("client"))
    try:
        return {name: query_health(session, name, timeout=5.0) for name in PIPELINE_SERVICES}
    finally:
        session.close()


def children(system) -> dict[str, int]:
    return {child.name: child.proc.pid for child in system.group.children if child.proc.poll() is None}


def test_malformed_payloads_on_every_key_each_role_may_publish(stack, dev_sequence):
    """Each role, with its own credentials, sends every malformed payload on every key it may publish (and asks
    every query it may ask with them). No process dies, every service still answers its health query, and every
    query is answered at once (with an error), not left to time out."""
    from twohr.bus import open_session
    from twohr.service import declare_publisher
    from twohr_app.access import role_grants

    system = stack["system"]
    pids = children(system)
    before = health_of_all(system)
    payloads = malformed_payloads(dev_frame(dev_sequence, ROBOT, "nosuchsession"))
    sent, asked, answered = Counter(), 0, 0
    for role, grants in role_grants().items():
        session = open_session(system.bus(role))
        try:
            for pattern in grants.publish:
                if pattern.startswith("@"):  # liveliness tokens, not data
                    continue
                key = pattern.replace("**", "fuzz/topic").replace("*", ROBOT, 1)
                publisher = declare_publisher(session, key, wait_for_subscribers=1.0)
                for payload in payloads:
                    publisher.put(payload)
                    sent[key.split("/", 2)[-1]] += 1
                publisher.undeclare()
            for pattern in grants.ask:
                key = pattern.replace("*", ROBOT, 1)
                for payload in payloads:
                    asked += 1
                    replies = list(session.get(key, payload=payload, timeout=10.0))
                    answered += bool(replies)
        finally:
            session.close()
    time.sleep(3.0)  # let the services work through their queues
    after = health_of_all(system)
    deaths = [name for name, pid in pids.items() if children(system).get(name) != pid]
    silent = [name for name, health in after.items() if health is None]
    received = {name: after[name]["received"] - before[name]["received"] for name in after if after[name]}
    errors = {name: after[name]["errors"] - before[name]["errors"] for name in after if after[name]}
    print(f"bus fuzzing: {sum(sent.values())} messages sent ({dict(sent)}), {asked} queries ({answered} answered); "
          f"{len(deaths)} process deaths, {len(silent)} missed health answers; received per service {received}; "
          f"unexpected errors per service {errors}")
    assert not deaths and not silent
    assert asked == answered
    assert all(received[name] >= len(payloads) for name in received), "the fuzz must reach every service"
    assert not any(errors.values()), "a malformed message raised an unexpected exception in a service"


def test_a_10_s_flood_from_an_outside_client_stays_bounded(stack, dev_sequence):
    """A client floods twohr/<robot>/camera with real frames of sessions nobody started and tries every other key
    for 10 s. Every service's memory stays bounded, nothing is recorded, and no process dies."""
    from twohr import keys
    from twohr.bus import open_session

    system, recordings = stack["system"], stack["recordings"]
    pids = children(system)
    rss_before = {name: rss_mb(pid) for name, pid in pids.items()}
    bytes_before = sum(f.stat().st_size for f in recordings.rglob("*") if f.is_file())
    frames = [dev_frame(dev_sequence, "flood", f"never{i:02d}", i) for i in range(20)]
    start = encode(ControlMsg(session_id="never00", robot_id="flood", frame_index=-1, stamp=0.0, command="start",
                              sequence=str(dev_sequence)))
    others = [keys.key("flood", stream) for stream in (*keys.STREAMS, keys.CONTROL, keys.MATCH_QUERY,
                                                        keys.DETECT_QUERY, keys.DYNAMICS_QUERY)]
    sent = Counter()
    client = open_session(system.bus("client"))
    try:
        deadline = time.monotonic() + 10.0
        i = 0
        while time.monotonic() < deadline:
            client.put(keys.key("flood", keys.RAW_CAMERA), frames[i % len(frames)])
            sent["camera"] += 1
            if i % 20 == 0:
                for key in others:
                    client.put(key, start if key.endswith(keys.CONTROL) else frames[0])
                    sent["other keys"] += 1
            i += 1
    finally:
        client.close()
    time.sleep(5.0)  # queues drain
    health = health_of_all(system)
    rss_after = {name: rss_mb(pid) for name, pid in children(system).items()}
    written = sum(f.stat().st_size for f in recordings.rglob("*") if f.is_file()) - bytes_before
    growth = {name: round(rss_after[name] - rss_before[name], 1) for name in rss_before if name in rss_after}
    print(f"10 s flood: {dict(sent)} messages ({sent['camera'] * len(frames[0]) / 1e6:.0f} MB on camera); RSS MB "
          f"before {({k: round(v) for k, v in rss_before.items()})}, growth {growth}; {written} bytes recorded; "
          f"source received {health['source'] and health['source']['received']}")
    assert children(system) == pids, "a process died"
    assert all(h is not None for h in health.values()), health
    assert health["source"]["received"] >= sent["camera"] // 2, "the flood must reach the source"
    assert all(g < 100 for g in growth.values()), growth
    assert written == 0 and not list(recordings.glob("never*")), "recorded a session the gateway never started"
