"""Bus message schemas: round trips, and clean rejection of malformed payloads."""

import numpy as np
import pytest

from twohr import keys
from twohr.config import PipelineConfig
from twohr.dataset import CAMERA_PRESETS
from twohr.messages import (
    ControlMsg,
    DynamicsMsg,
    FrameMsg,
    KeypointsMsg,
    MessageError,
    PoseMsg,
    decode,
    encode,
    encoded_image,
    split,
)

IDS = {"session_id": "s1", "robot_id": "robot_1", "frame_index": 7, "stamp": 1548339819.874}


def test_frame_round_trip_png_and_raw():
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)
    depth = rng.integers(0, 60000, (48, 64), dtype=np.uint16)
    msg = FrameMsg(**IDS, camera=CAMERA_PRESETS["bonn"])
    for enc in ("png", "raw"):
        out, arrays = decode(encode(msg, {"rgb": rgb, "depth": depth}, {"rgb": enc, "depth": enc}), FrameMsg)
        assert out == msg
        assert np.array_equal(arrays["rgb"], rgb) and np.array_equal(arrays["depth"], depth)


def test_encoded_blob_passes_through_untouched(dev_sequence):
    import cv2

    jpg = sorted((dev_sequence / "rgb").iterdir())[0]
    data = jpg.read_bytes()
    expected = cv2.cvtColor(cv2.imread(str(jpg)), cv2.COLOR_BGR2RGB)
    depth = np.zeros((480, 640), np.uint16)
    payload = encode(FrameMsg(**IDS, camera=CAMERA_PRESETS["bonn"]), {"depth": depth},
                     blobs={"rgb": encoded_image("rgb", data, "jpeg", "uint8", expected.shape)})
    _, parts = split(payload)
    assert dict((s.name, b) for s, b in parts)["rgb"] == data
    _, arrays = decode(payload)
    assert np.array_equal(arrays["rgb"], expected)  # identical pixels to reading the file


def test_keypoints_dynamics_pose_control_round_trip():
    rng = np.random.default_rng(1)
    kp = {"xy": rng.random((10, 2), dtype=np.float32), "descriptors": rng.random((10, 128), dtype=np.float32),
          "scores": rng.random(10, dtype=np.float32)}
    out, arrays = decode(encode(KeypointsMsg(**IDS, width=640, height=480), kp))
    assert isinstance(out, KeypointsMsg) and all(np.array_equal(arrays[k], v) for k, v in kp.items())
    dyn = {"boxes": np.zeros((0, 4), np.float32), "scores": np.zeros(0, np.float32),
           "class_ids": np.zeros(0, np.int64), "mask": np.zeros((48, 64), np.uint8)}
    out, arrays = decode(encode(DynamicsMsg(**IDS), dyn, {"mask": "png"}))
    assert arrays["boxes"].shape == (0, 4) and arrays["mask"].shape == (48, 64)
    pose = PoseMsg(**IDS, position=[1, 2, 3], orientation=[0, 0, 0, 1], status="tracking", elapsed_ms={"pnp": 1.5})
    assert decode(encode(pose))[0] == pose
    control = ControlMsg(**IDS, command="start", sequence="/data/x", config=PipelineConfig())
    assert decode(encode(control))[0].config == PipelineConfig()


def test_missing_required_array_and_wrong_type():
    payload = encode(KeypointsMsg(**IDS, width=1, height=1), {"xy": np.zeros((1, 2), np.float32)})
    with pytest.raises(MessageError, match="lacks arrays"):
        decode(payload)
    pose = encode(PoseMsg(**IDS, position=[0, 0, 0], orientation=[0, 0, 0, 1], status="x"))
    with pytest.raises(MessageError, match="expected twohr.Frame"):
        decode(pose, FrameMsg)


def test_malformed_payloads_never_escape_as_other_errors():
    rng = np.random.default_rng(2)
    good = encode(FrameMsg(**IDS, camera=CAMERA_PRESETS["bonn"]),
                  {"rgb": np.zeros((8, 8, 3), np.uint8), "depth": np.zeros((8, 8), np.uint16)},
                  {"rgb": "jpeg", "depth": "png"})
    cases = [b"", b"2HR", good[:-1], good + b"\0", b"XYZ" + good[3:], bytes([*good[:3], 9, *good[4:]])]
    cases += [bytes(rng.integers(0, 256, n, dtype=np.uint8)) for n in (5, 64, 4096)]
    for _ in range(200):  # random bit flips anywhere
        corrupt = bytearray(good)
        corrupt[rng.integers(0, len(good))] ^= 1 << rng.integers(0, 8)
        cases.append(bytes(corrupt))
    rejected = 0
    for payload in cases:
        try:
            decode(payload)
        except MessageError:
            rejected += 1
    assert rejected >= 9  # every structural case; some bit flips in image data still decode


def test_ids_are_validated():
    with pytest.raises(ValueError):
        PoseMsg(**{**IDS, "robot_id": "../etc"}, position=[0, 0, 0], orientation=[0, 0, 0, 1], status="x")
    with pytest.raises(ValueError):
        keys.key("bad robot", "pose")
    assert keys.key("r1", "pose") == "twohr/r1/pose"
    assert keys.parse("twohr/r1/rpc/match") == ("r1", "rpc/match")


def test_a_received_frame_decodes_each_image_on_first_use(dev_sequence):
    """A frame from the bus keeps its message for remote stages and decodes only the images a stage reads: a
    corrupt colour image fails when (and only when) the colour image is read."""
    from twohr.dataset import depth_in_metres
    from twohr.messages import received_frame

    camera = CAMERA_PRESETS["bonn"]
    jpg = sorted((dev_sequence / "rgb").iterdir())[0].read_bytes()
    depth = np.full((480, 640), 5000, np.uint16)
    payload = encode(FrameMsg(**IDS, camera=camera), {"depth": depth},
                     blobs={"rgb": encoded_image("rgb", jpg, "jpeg", "uint8", (480, 640, 3))})
    header, frame = received_frame(payload)
    assert (frame.index, frame.stamp, frame.message) == (7, IDS["stamp"], payload)
    assert np.array_equal(frame.depth, depth_in_metres(depth, camera))
    assert frame.rgb.shape == (480, 640, 3) and frame.gray.shape == (480, 640)
    assert abs(float(frame.gray.astype(float).mean()) - float(frame.rgb.mean())) < 5  # the same image, in grey

    broken = encode(FrameMsg(**IDS, camera=camera), {"depth": depth},
                    blobs={"rgb": encoded_image("rgb", b"not a jpeg", "jpeg", "uint8", (480, 640, 3))})
    _, frame = received_frame(broken)
    assert frame.depth.shape == (480, 640)  # the depth alone is fine
    with pytest.raises(MessageError, match="corrupt"):
        _ = frame.rgb


def test_an_image_claiming_more_pixels_than_the_cap_is_refused_before_it_is_decoded():
    import cv2

    from twohr.messages import MAX_IMAGE_PIXELS

    side = int(MAX_IMAGE_PIXELS**0.5) + 1
    ok, png = cv2.imencode(".png", np.zeros((8, 8), np.uint16))
    claimed = encode(FrameMsg(**IDS, camera=CAMERA_PRESETS["bonn"]),
                     blobs={"rgb": encoded_image("rgb", png.tobytes(), "png", "uint8", (side, side, 3)),
                            "depth": encoded_image("depth", png.tobytes(), "png", "uint16", (8, 8))})
    with pytest.raises(MessageError, match="at most"):
        decode(claimed)
