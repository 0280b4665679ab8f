"""The tracker service on a real Zenoh router, with the real detector and matcher services beside it, fed real frames:
the end of one robot's session holds up no other robot's frames, and a session in a named map keeps the map, not
the map file it was built from."""

from __future__ import annotations

import gc
import threading
import time

import numpy as np
import pytest

from twohr import keys
from twohr.bus import BusConfig, open_session
from twohr.config import PipelineConfig, load_config
from twohr.dataset import RGBDSequence
from twohr.mapclient import no_map
from twohr.mapfile import MapArrays, MapFile, encode_map, read_map
from twohr.mapstore import MapEntry
from twohr.messages import ControlMsg, PathMsg, PoseMsg, StatusMsg, decode, encode
from twohr.service import declare_publisher
from twohr_services.detector.service import DetectorService
from twohr_services.matcher.service import MatcherService
from twohr_services.source.core import frame_payloads
from twohr_services.tracker.service import TrackerService

# half-resolution 2HR keeps the keyframe jobs quick; no masks
OVERRIDES = {"detector.input_scale": 0.5, "yolo.enabled": False}
WAIT_S = 120.0  # for what must come (a loaded machine is slow, never this slow)


class MapStore:
    """The map store's two queries on the bus (the map room serves them in the system, :mod:`twohr.mapclient`): a
    map's bytes, and a save, whose answer (the map's entry) waits while ``hold`` is clear (an event the test sets)."""

    def __init__(self, session, hold_s: float) -> None:
        self.maps: dict[str, bytes] = {}
        self.saves: list[tuple[str, bytes]] = []
        self.saving = threading.Event()  # a save has come and waits for its answer
        self.hold = threading.Event()
        self.hold.set()
        self.hold_s = hold_s  # below the map client's TIMEOUT_S: a held save is still answered
        self.answered_after_release: list[bool] = []
        self.queryables = [session.declare_queryable(f"{keys.MAPS_PREFIX}/*", self._read),
                           session.declare_queryable(f"{keys.MAPS_PREFIX}/*/save", self._save)]

    def _read(self, query) -> None:
        name = keys.parse_map_key(query.key_expr)
        if name in self.maps:
            query.reply(query.key_expr, self.maps[name])
        else:
            query.reply_err(no_map(name).encode())

    def _save(self, query) -> None:
        name = keys.parse_map_key(query.key_expr, save=True)
        self.saves.append((name, query.payload.to_bytes()))
        self.saving.set()
        self.answered_after_release.append(self.hold.wait(self.hold_s))
        data = self.maps[name] = query.payload.to_bytes()
        header = read_map(data).header
        entry = MapEntry(name=name, version=1, versions=[1], keyframes=header.keyframes, landmarks=header.landmarks,
                         size_bytes=len(data), built_by=header.built_by, created=header.created,
                         detector_model=header.detector_model)
        query.reply(query.key_expr, entry.model_dump_json().encode())

    def close(self) -> None:
        for queryable in self.queryables:
            queryable.undeclare()


class Robots:
    """An outside client of the bus: starts and stops sessions, sends frames, and keeps every robot's poses, paths
    and statuses."""

    def __init__(self, bus: BusConfig) -> None:
        self.session = open_session(bus)
        self.lock = threading.Lock()
        self.received: list[tuple[str, object]] = []  # (robot, message) in the order they came
        self.publishers: dict[str, object] = {}
        self.subscribers = [self.session.declare_subscriber(keys.all_robots(topic), self._on(schema))
                            for topic, schema in (("pose", PoseMsg), ("path", PathMsg), ("status", StatusMsg))]

    def _on(self, schema):
        def callback(sample) -> None:
            message, _ = decode(sample.payload.to_bytes(), schema, only=())
            with self.lock:
                self.received.append((message.robot_id, message))
        return callback

    def put(self, key: str, payload: bytes) -> None:
        if key not in self.publishers:
            self.publishers[key] = declare_publisher(self.session, key)
        self.publishers[key].put(payload)

    def control(self, robot: str, session_id: str, command: str, config: PipelineConfig, **fields) -> None:
        self.put(keys.key(robot, keys.CONTROL), encode(ControlMsg(
            session_id=session_id, robot_id=robot, frame_index=-1, stamp=time.time(), command=command,
            sequence="dev", config=config, **fields)))

    def messages(self, robot: str, kind: type) -> list:
        with self.lock:
            return [m for r, m in self.received if r == robot and isinstance(m, kind)]

    def wait_for(self, what, timeout: float = WAIT_S):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            found = what()
            if found:
                return found
            time.sleep(0.05)
        return None

    def close(self) -> None:
        for sub in self.subscribers:
            sub.undeclare()
        self.session.close()


@pytest.fixture(scope="module")
def stack(zenoh_router):
    """The tracker, detector and matcher services in this process, a map store, and a client."""
    bus = BusConfig(connect=[zenoh_router])
    stop = threading.Event()
    tracker = TrackerService(bus)
    services = [tracker, DetectorService(bus), MatcherService(bus)]
    threads = [threading.Thread(target=service.run, args=(stop,), daemon=True) for service in services]
    for thread in threads:
        thread.start()
    client = Robots(bus)
    store = MapStore(client.session, hold_s=25.0)
    alive = client.session.liveliness()
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:  # the services declare themselves alive once warm
        names = {keys.parse_replica_key(r.ok.key_expr)[0] for r in alive.get(keys.alive_key("*")) if r.ok}
        if {"tracker", "detector", "matcher"} <= names:
            break
        time.sleep(0.2)
    yield tracker, client, store
    store.close()
    client.close()
    stop.set()
    for thread in threads:
        thread.join(timeout=60)


def _start(tracker: TrackerService, client: Robots, robot: str, session_id: str, **fields) -> PipelineConfig:
    config = load_config(None, OVERRIDES)
    client.control(robot, session_id, "start", config, **fields)
    assert client.wait_for(lambda: session_id in tracker.session_configs), f"{session_id} never started"
    return config


def _frames(dev_sequence, robot: str, session_id: str, count: int, start: int = 0) -> list[bytes]:
    return [item.payload for item in frame_payloads(RGBDSequence(dev_sequence), session_id, robot, start, count)]


def test_a_session_that_ends_holds_up_no_other_robots_frames(stack, dev_sequence):
    """Robot r1's session ends (final bundle adjustment, re-measurement, smoothing, final path, then its map saved);
    the store holds the save's answer until robot r2's first frame has its pose. On the per-frame thread, r2's
    frame would wait behind the save until the store gave up holding it: no pose while the save is held."""
    tracker, client, store = stack
    _start(tracker, client, "r1", "ending", map_name="hall", map_mode="build")
    _start(tracker, client, "r2", "going-on")
    for payload in _frames(dev_sequence, "r1", "ending", 30):
        client.put(keys.key("r1", "frames"), payload)
    assert client.wait_for(lambda: len(client.messages("r1", PoseMsg)) == 30), "r1's frames were not all tracked"
    store.hold.clear()
    store.saving.clear()
    client.control("r1", "ending", "stop", PipelineConfig())
    assert store.saving.wait(WAIT_S), "r1's map was never saved"
    assert client.wait_for(lambda: any(m.final for m in client.messages("r1", PathMsg))), "no final path"
    jobs = [m for m in client.messages("r1", StatusMsg) if m.state == "keyframe_jobs"]
    assert jobs and jobs[-1].counters["count"] > 0 and jobs[-1].counters["ms_job_p90"] >= jobs[-1].counters[
        "ms_job_median"] > 0, jobs  # each keyframe job's whole latency, for `twohr bench --bus`

    client.put(keys.key("r2", "frames"), _frames(dev_sequence, "r2", "going-on", 1, start=100)[0])
    posed = client.wait_for(lambda: client.messages("r2", PoseMsg), timeout=20.0)
    store.hold.set()
    assert posed, "r2's frame waited for the end of r1's session"
    assert client.wait_for(lambda: store.answered_after_release)
    assert store.answered_after_release[-1]  # the save was still held (not given up) when r2's pose came
    assert read_map(store.saves[-1][1]).header.name == "hall"
    client.control("r2", "going-on", "stop", PipelineConfig())


def test_a_session_in_a_named_map_keeps_the_map_not_the_file(stack, dev_sequence, tiny_map):
    """A session that extends a map fetched from the store tracks in the :class:`Map` built from it; the fetched
    file (its arrays, as large again as the map) is not kept beside it, yet the saved map still names its parent."""
    tracker, client, store = stack
    camera = RGBDSequence(dev_sequence).camera
    stored = tiny_map("shelf", camera)
    store.maps["shelf"] = encode_map(stored)
    parent = f"shelf@{stored.header.created:.3f}"
    del stored
    _start(tracker, client, "r3", "extending", map_name="shelf", map_mode="extend")
    for payload in _frames(dev_sequence, "r3", "extending", 2):
        client.put(keys.key("r3", "frames"), payload)
    assert client.wait_for(lambda: len([m for m in client.messages("r3", StatusMsg) if m.state == "relocalising"]) == 2)
    assert tracker.sessions["extending"].track.schedule.map  # the map it localizes in
    gc.collect()
    assert not [type(o).__name__ for o in gc.get_objects() if isinstance(o, (MapFile, MapArrays))]
    saves = len(store.saves)
    client.control("r3", "extending", "stop", PipelineConfig())
    assert client.wait_for(lambda: len(store.saves) > saves), "the extended map was never saved"
    saved = read_map(store.saves[-1][1]).header
    assert (saved.name, saved.parent) == ("shelf", parent)


def test_one_match_query_answers_every_candidate_set(stack):
    """A relocalisation's candidate keyframes go to the matcher service in one query, answered per set with the
    matches that one query per set gives; sizes that do not add up are refused."""
    from types import SimpleNamespace

    from twohr.errors import TwohrError
    from twohr_services.tracker.remote import RemoteMatcher

    tracker, client, _ = stack
    _start(tracker, client, "r5", "sets")
    replies = []
    listener = client.session.declare_subscriber(keys.key("r5", "matches"), lambda sample: replies.append(1))
    rng = np.random.default_rng(5)
    frame_desc = rng.normal(size=(120, 128)).astype(np.float32)
    frame_desc /= np.linalg.norm(frame_desc, axis=1, keepdims=True)
    sets = [frame_desc[rng.permutation(120)[:n]] + 0.02 * rng.normal(size=(n, 128)).astype(np.float32)
            for n in (80, 40, 60)]
    matcher = RemoteMatcher(tracker.networks.replicas["matcher"], "r5", "sets")
    frame = SimpleNamespace(index=7, stamp=1.0)
    one_each = [matcher(frame, frame_desc, desc_b) for desc_b in sets]
    assert client.wait_for(lambda: len(replies) == 3)
    together = matcher.sets(frame, frame_desc, sets)
    assert client.wait_for(lambda: len(replies) == 4)  # one query, one reply
    assert [len(m) for m in together] == [len(m) for m in one_each] and min(len(m) for m in together) > 30
    for a, b in zip(one_each, together, strict=True):
        assert np.array_equal(a.idx_a, b.idx_a) and np.array_equal(a.idx_b, b.idx_b)
    with pytest.raises(TwohrError, match="do not add up"):
        matcher._ask(frame, "bad", {"desc_a": frame_desc, "desc_b": sets[0], "desc_b_sizes": np.array([5, 5])})
    listener.undeclare()
    client.control("r5", "sets", "stop", PipelineConfig())
