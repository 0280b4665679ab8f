"""Shared fixtures: the real dev sequence and models from ../shared, and small synthetic sequences."""

from __future__ import annotations

import collections
import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from twohr.bus import free_port
from twohr.paths import DEV_SEQUENCE as DEV_SEQUENCE_PATH

REPO = Path(__file__).resolve().parent
SHARED = REPO.parent / "shared"
DEV_SEQUENCE = Path(os.path.normpath(REPO / DEV_SEQUENCE_PATH))  # the commands' default, made absolute
MODEL_MIRROR = SHARED / "models"


def read_until(proc: subprocess.Popen, prefix: str) -> list[str]:
    """The lines ``proc`` prints up to and including the first that starts with ``prefix`` (all it printed, if
    it exits first); what it prints after that is read and dropped in the background, because a pipe nobody reads
    fills (64 KiB: a few hundred of uvicorn's access lines) and then the process's next print blocks it."""
    lines = []
    for line in proc.stdout:
        lines.append(line)
        if line.startswith(prefix):
            break
    threading.Thread(target=collections.deque, args=(proc.stdout, 0), name="drain", daemon=True).start()
    return lines


@pytest.fixture(scope="session")
def dev_sequence() -> Path:
    if not DEV_SEQUENCE.is_dir():
        pytest.fail(f"the real dev sequence is required at {DEV_SEQUENCE} (../shared beside the repo)")
    return DEV_SEQUENCE


#: the config the stack tests' sessions run (the networks' input at half size)
FAST_CONFIG = {"detector.input_scale": 0.5}
#: the share of this host's replay rate (``twohr run``, paced by poses) its live cameras run at in the tests: a
#: live stack adds the bus and its processes, and a live camera's frames must not outrun its keyframe jobs there
LIVE_SHARE = 0.8
#: the camera rate of the dev frames and the lowest rate the tests run them at
RECORDED_HZ, SLOWEST_HZ = 30.0, 5.0


@pytest.fixture(scope="session")
def camera_hz(dev_sequence, tmp_path_factory, request) -> float:
    """The frame rate of the tests' live cameras and real-rate replays on this host: the dev frames' 30 Hz where the
    host's stack carries a robot at that rate, else what it carries. CPUs differ severalfold in the keyframe networks
    (a keyframe job at half input size 0.86 s on one 2-core AVX2 EPYC; 0.24-0.31 s at full size on the AMX Xeon), and
    a test of what the fleet does (who gets which frames, fail-over, TLS) must not fail on a slow one for its speed,
    which ``twohr bench`` measures.
    Measured once per test session: ``twohr run`` on 90 dev frames with :data:`FAST_CONFIG`, paced by its poses."""
    out = tmp_path_factory.mktemp("camera_hz")
    sets = [arg for key, value in FAST_CONFIG.items() for arg in ("--set", f"{key}={value}")]
    done = subprocess.run([str(Path(sys.executable).with_name("twohr")), "run", "--sequence", str(dev_sequence),
                           "--frames", "90", *sets, "--out", str(out), "--quiet"],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    replay_fps = json.loads((out / "summary.json").read_text())["fps"]
    hz = float(min(RECORDED_HZ, max(SLOWEST_HZ, round(LIVE_SHARE * replay_fps))))
    terminal = request.config.pluginmanager.get_plugin("terminalreporter")
    if terminal is not None:
        terminal.write_line(f"\nlive cameras in the tests run at {hz:g} Hz on this host (its replay of the dev "
                            f"frames: {replay_fps:.1f} FPS)")
    return hz


@pytest.fixture(scope="session")
def tiny_map():
    """``tiny_map(name, camera)``: a valid map file of one keyframe observing three landmarks, built with the default
    detector model (for the map store and its routes; real maps come from the tracker tests)."""
    import numpy as np

    from twohr.config import load_config
    from twohr.mapfile import MapArrays, MapFile, MapHeader

    def make(name: str, camera) -> MapFile:
        arrays = MapArrays(
            keyframe_poses=np.eye(4)[None], keyframe_stamps=np.zeros(1), keyframe_culled=np.zeros(1, bool),
            keyframe_first=np.array([0, 3]), keypoint_xy=np.ones((3, 2), np.float32),
            keypoint_depth=np.ones(3, np.float32), keypoint_landmark=np.arange(3),
            landmark_positions=np.ones((3, 3)), landmark_descriptors=np.ones((3, 128), np.float32),
            landmark_accepted=np.zeros(3, np.int64), landmark_rejected=np.zeros(3, np.int64),
            landmark_bad=np.zeros(3, bool))
        header = MapHeader(name=name, camera=camera, detector_model=load_config(None).detector.model,
                           descriptor_dim=128, descriptor_dtype="float32", keyframes=1, landmarks=3, built_by="test")
        return MapFile(header, arrays)

    return make


@pytest.fixture(scope="session")
def model_mirror() -> Path:
    if not MODEL_MIRROR.is_dir():
        pytest.fail(f"the model mirror is required at {MODEL_MIRROR}")
    return MODEL_MIRROR


@pytest.fixture(scope="session")
def synthetic_sequence(tmp_path_factory) -> Path:
    """60 frames at 320x240 with one moving occluder; exact depth and ground truth."""
    from twohr.synthetic import SyntheticSpec, generate

    return generate(tmp_path_factory.mktemp("synth") / "synthetic_room", SyntheticSpec(frames=60))


@pytest.fixture(scope="session")
def static_synthetic_sequence(tmp_path_factory) -> Path:
    """30 frames, no moving objects."""
    from twohr.synthetic import SyntheticSpec, generate

    return generate(tmp_path_factory.mktemp("synth_static") / "synthetic_static",
                    SyntheticSpec(frames=30, occluders=0, seed=3))


@pytest.fixture(scope="session")
def synthetic_room(tmp_path_factory):
    """``synthetic_room(spec) -> Path``: the sequence :func:`twohr.synthetic.generate` renders for ``spec``, rendered
    once per session for every test that asks for an equal spec (360 frames take half a minute to render); tests
    read it and never write into it."""
    from twohr.synthetic import generate

    rendered: dict[str, Path] = {}

    def room(spec) -> Path:
        if repr(spec) not in rendered:  # a dataclass's repr names every field
            rendered[repr(spec)] = generate(tmp_path_factory.mktemp("synthetic_room") / "room", spec)
        return rendered[repr(spec)]

    return room


class KeyframeNetworks:
    """Each keyframe network (``detector.model``: f32, no latency budget, the default input scale) built once, and
    its keypoints of a dev frame detected once; tests only read them."""

    def __init__(self, sequence: Path) -> None:
        from twohr.dataset import RGBDSequence

        self.sequence = RGBDSequence(sequence)
        self._detectors: dict = {}
        self._keypoints: dict = {}

    def detector(self, name: str):
        from twohr.config import DetectorConfig
        from twohr_services.detector.core import R2D2Detector

        if name not in self._detectors:
            self._detectors[name] = R2D2Detector(DetectorConfig(model=name, latency_budget_ms=None, precision="f32"))
        return self._detectors[name]

    def keypoints(self, name: str, index: int):
        if (name, index) not in self._keypoints:
            self._keypoints[name, index] = self.detector(name).detect(self.sequence.read(index).rgb)
        return self._keypoints[name, index]


@pytest.fixture(scope="session")
def keyframe_networks(dev_sequence) -> KeyframeNetworks:
    """:class:`KeyframeNetworks` of the dev sequence, for the session: the detector's tests and the Siamese
    matcher's read the same networks' keypoints of the same frames."""
    return KeyframeNetworks(dev_sequence)


@pytest.fixture(scope="session")
def zenoh_router():
    """A real Zenoh router on a free loopback port; yields its endpoint."""
    from twohr.bus import start_router

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = start_router([endpoint])
    yield endpoint
    router.close()


@pytest.fixture
def bus_config(zenoh_router):
    from twohr.bus import BusConfig

    return BusConfig(connect=[zenoh_router])


@pytest.fixture
def foxglove_listener():
    """Opens :class:`twohr.foxglove_live.FoxgloveClient` clients on a URL; closes them after the test."""
    from twohr.foxglove_live import FoxgloveClient

    opened = []

    def open_listener(url: str, subprotocol: str = "foxglove.websocket.v1") -> FoxgloveClient:
        opened.append(FoxgloveClient(url, subprotocol))
        return opened[-1]

    yield open_listener
    for listener in opened:
        listener.close()
