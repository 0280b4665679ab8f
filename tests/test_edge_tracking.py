"""A robot that tracks itself (``twohr camera --edge``), with real processes: the stack (``start_system``), the
robot's camera and its own tracker in one process, a real TCP link between them that the test cuts and mends, and
on a fleet's keys a real router whose access-control list gives a robot's own tracker its own keys and no other's."""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest

from twohr.bus import free_port, open_session
from twohr.dataset import RGBDSequence
from twohr.evaluation import evaluate
from twohr.messages import StatusMsg, decode
from twohr.trajectory import read_tum

FRAMES = 300
OUTAGE_S = 3.0


class Link:
    """A TCP link on loopback to the router's ``port``, which the test cuts (every connection closed, new ones
    refused) and mends: the robot's link to the stack."""

    def __init__(self, port: int) -> None:
        self.target, self.up, self.open = port, True, []
        self.lock = threading.Lock()
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                near, _ = self.server.accept()
            except OSError:
                return
            try:
                if not self.up:
                    raise OSError("cut")
                far = socket.create_connection(("127.0.0.1", self.target))
            except OSError:
                near.close()
                continue
            with self.lock:
                self.open += [near, far]
            for source, target in ((near, far), (far, near)):
                threading.Thread(target=self._pump, args=(source, target), daemon=True).start()

    @staticmethod
    def _pump(source: socket.socket, target: socket.socket) -> None:
        try:
            while data := source.recv(65536):
                target.sendall(data)
        except OSError:
            pass
        for end in (source, target):
            try:
                end.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def cut(self) -> None:
        self.up = False
        with self.lock:
            for end in self.open:
                try:
                    end.shutdown(socket.SHUT_RDWR)
                    end.close()
                except OSError:
                    pass
            self.open.clear()

    def mend(self) -> None:
        self.up = True

    def close(self) -> None:
        self.cut()
        self.server.close()


@pytest.fixture(scope="module")
def stack(tmp_path_factory, dev_sequence):
    from twohr_app.fleet import write_client_config
    from twohr_app.supervisor import start_system

    scratch = tmp_path_factory.mktemp("edge")
    router_port, port = free_port(), free_port()
    router = f"tcp/127.0.0.1:{router_port}"
    system = start_system(router, [str(dev_sequence.parent)], str(scratch / "recordings"), "127.0.0.1", port,
                          timeout=180, max_robots=1)
    link = Link(router_port)
    # a stack without keys: every role is this host's; the robot's own tracker joins as a tracker, over its link
    own = write_client_config(scratch / "T.json5", f"tcp/127.0.0.1:{link.port}", system.credentials, role="tracker")
    observer = write_client_config(scratch / "C.json5", router, system.credentials)
    yield {"system": system, "url": f"http://127.0.0.1:{port}", "link": link, "own": own, "observer": observer,
           "scratch": scratch}
    link.close()
    system.stop()


def test_a_robot_that_tracks_itself_sends_no_frame_and_keeps_tracking_through_a_cut_link(stack, dev_sequence,
                                                                                          camera_hz):
    from twohr.bus import BusConfig

    sequence = RGBDSequence(dev_sequence)
    seen: dict[str, int] = {"frames": 0, "camera": 0}
    statuses: list[tuple[str, str]] = []
    observer = open_session(BusConfig(config_file=stack["observer"]))

    def count(sample) -> None:
        seen[str(sample.key_expr).split("/")[2]] += 1

    def status(sample) -> None:
        message, _ = decode(sample.payload.to_bytes(), StatusMsg)
        statuses.append((message.service, message.state))

    subscribers = [observer.declare_subscriber("twohr/*/frames", count),
                   observer.declare_subscriber("twohr/*/camera", count),
                   observer.declare_subscriber("twohr/r1/status", status)]
    err = open(stack["scratch"] / "camera.err", "w")
    camera = subprocess.Popen([sys.executable, "-m", "twohr_app", "camera", "--replay", str(dev_sequence), "--rate",
                               f"{camera_hz:g}", "--robot", "r1", "--zenoh-config", str(stack["own"]), "--edge",
                               "--frames", str(FRAMES), "--linger", "60"], stdout=subprocess.PIPE, stderr=err,
                              text=True)
    try:
        assert "tracks itself (tracker edge+r1)" in camera.stdout.readline()
        with httpx.Client(base_url=stack["url"], timeout=60) as client:
            started = client.post("/sessions", json={"source": "camera", "robot_id": "r1", "record": False})
            assert started.status_code == 201, started.text
            session = started.json()
            assert session["tracker"] == "edge+r1", session  # placed on the robot's own tracker
            time.sleep(3.0)
            trackers = {t["replica"]: t["robots"] for t in client.get("/healthz").json()["trackers"]}
            assert trackers.pop("edge+r1") == ["r1"] and all(robots == [] for robots in trackers.values()), trackers
            stack["link"].cut()
            time.sleep(OUTAGE_S)
            stack["link"].mend()
            deadline = time.monotonic() + 30 + FRAMES / camera_hz
            while (client.get(f"/sessions/{session['id']}").json()["frames_sent"] or 0) < FRAMES - 1:
                assert time.monotonic() < deadline, "the robot did not count its frames into the session"
                time.sleep(0.5)
            time.sleep(2.0)
            online = client.get(f"/sessions/{session['id']}").json()["frames"]
            assert client.delete(f"/sessions/{session['id']}").status_code == 200
            served = client.get(f"/sessions/{session['id']}/trajectory")
        out, _ = camera.communicate(timeout=120)
    finally:
        if camera.poll() is None:
            camera.kill()
        err.close()
        for subscriber in subscribers:
            subscriber.undeclare()
        observer.close()
    assert camera.returncode == 0, (stack["scratch"] / "camera.err").read_text()[-3000:]
    assert seen == {"frames": 0, "camera": 0}, seen  # no frame of the robot's crossed the bus
    sent = int(out.split(" bytes/s upstream")[0].rsplit("(", 1)[1])
    assert 0 < sent <= 600_000, out  # its keyframes' colour images and its results: COVINS's order, not 5 MB/s
    assert served.headers["x-twohr-trajectory"] == "refined"
    path = stack["scratch"] / "served.txt"
    path.write_text(served.text)
    refined = read_tum(path)
    # the poses made while the link was cut never reached the stack, but the robot tracked on: its final trajectory
    # has them, and it said it lost the stack and found it again
    assert len(refined) >= 0.85 * FRAMES and len(refined) >= online + 0.5 * OUTAGE_S * camera_hz, (len(refined),
                                                                                                online)
    assert ("tracker", "online") in statuses, statuses
    assert "the stack is out of reach: tracking in the local map" in (stack["scratch"] / "camera.err").read_text()
    extrinsic = sequence.default_gt_extrinsic()
    ate = evaluate(sequence.ground_truth(extrinsic), refined, gt_extrinsic=extrinsic)[0].ate.rmse
    assert ate <= 0.03, ate


def test_server_stages_are_configuration_and_a_bad_one_is_one_line(dev_sequence):
    done = subprocess.run([sys.executable, "-m", "twohr_app", "camera", "--replay", str(dev_sequence), "--edge",
                           "--server-stages", "detector,planner"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "planner is no network stage" in done.stderr and "Traceback" not in done.stderr


@pytest.fixture(scope="module")
def edge_keys(tmp_path_factory) -> tuple[Path, dict[str, Path]]:
    folder = tmp_path_factory.mktemp("edge_fleet") / "K"
    twohr = [sys.executable, "-m", "twohr_app", "keys"]
    assert subprocess.run([*twohr, "init", str(folder)], capture_output=True).returncode == 0
    bundles = {}
    for robot, edge in (("e", True), ("f", True), ("p", False)):
        bundles[robot] = folder.parent / f"{robot}.bundle"
        done = subprocess.run([*twohr, "add", str(folder), robot, "--out", str(bundles[robot]),
                               *(["--edge"] if edge else [])], capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
    listed = subprocess.run([*twohr, "list", str(folder)], capture_output=True, text=True).stdout
    assert [line.endswith("(own tracker)") for line in listed.splitlines()[1:4]] == [True, True, False], listed
    return folder, bundles


def test_a_robots_own_tracker_publishes_its_own_results_and_no_other_robots(edge_keys):
    """Robots e and f run their own trackers (``keys add --edge``), p does not. Each own tracker publishes its robot's
    poses and status, hears its sessions start, asks the detector for its own keyframes and holds its tracker token;
    f cannot do any of that for e, and p cannot publish a pose at all. Of a shared map: e sends its own keyframes to
    the map server, f cannot send them for e nor p its own, and only the map server announces a merge (e hears it,
    e's forged one never lands)."""
    from twohr.bus import BusConfig
    from twohr.identity import load_identity
    from twohr.keys import alive_key, edge_replica, replica_query
    from twohr_app.fleet import Fleet
    from twohr_app.fleet_router import FleetRouter

    def _client(identity):
        return open_session(BusConfig(connect=[endpoint], identity=identity, user=None, password=None,
                                      config_file=None, shared_memory=False))

    folder, bundles = edge_keys
    fleet = Fleet(folder)
    endpoint = f"tls/127.0.0.1:{free_port()}"
    router = FleetRouter(fleet.service_folder("router"), [endpoint])
    sessions = []
    try:
        gateway, detector = _client(fleet.identity("gateway")), _client(fleet.identity("detector"))
        mapserver = _client(fleet.identity("mapserver"))
        e, f, p = (_client(load_identity(bundles[name])) for name in "efp")
        sessions += [gateway, detector, mapserver, e, f, p]
        shared: list[tuple[str, bytes]] = []
        mapserver.declare_subscriber("twohr/*/keyframes", lambda s: shared.append((str(s.key_expr),
                                                                                   s.payload.to_bytes())))
        merges: dict[str, list[bytes]] = {"e": [], "gateway": []}
        e.declare_subscriber("twohr/maps/*/merged", lambda s: merges["e"].append(s.payload.to_bytes()))
        gateway.declare_subscriber("twohr/maps/*/merged", lambda s: merges["gateway"].append(s.payload.to_bytes()))
        results: list[tuple[str, bytes]] = []
        gateway.declare_subscriber("twohr/*/pose", lambda s: results.append((str(s.key_expr), s.payload.to_bytes())))
        gateway.declare_subscriber("twohr/*/status", lambda s: results.append((str(s.key_expr),
                                                                               s.payload.to_bytes())))
        trackers: list[str] = []
        gateway.liveliness().declare_subscriber(alive_key("tracker"), lambda s: trackers.append(
            str(s.key_expr).rsplit("/", 1)[1]))
        controls: dict[str, list[bytes]] = {"e": [], "f": []}
        e.declare_subscriber("twohr/e/control", lambda s: controls["e"].append(s.payload.to_bytes()))
        f.declare_subscriber("twohr/e/control", lambda s: controls["f"].append(s.payload.to_bytes()))
        detector.declare_queryable("twohr/*/rpc/detect/d1", lambda q: q.reply(q.key_expr, b"kp"))
        mapserver.declare_queryable("twohr/maps/*/save", lambda q: q.reply(q.key_expr, b"saved"))
        replicas_seen: dict[str, list[str]] = {"e": [], "p": []}
        for name, session in (("e", e), ("p", p)):
            session.liveliness().declare_subscriber(alive_key("detector"), lambda s, n=name: replicas_seen[n].append(
                str(s.key_expr)))
        time.sleep(1.0)
        detector_token = detector.liveliness().declare_token(alive_key("detector", "d1"))
        tokens = [e.liveliness().declare_token(alive_key("tracker", edge_replica("e"))),
                  f.liveliness().declare_token(alive_key("tracker", edge_replica("e"))),  # f posing as e's tracker
                  p.liveliness().declare_token(alive_key("tracker", edge_replica("p")))]
        gateway.put("twohr/e/control", b"start")
        e.put("twohr/e/pose", b"e's pose")
        e.put("twohr/e/status", b"e's status")
        f.put("twohr/e/pose", b"f forging e's pose")
        f.put("twohr/f/pose", b"f's pose")
        p.put("twohr/p/pose", b"p may not publish poses")
        e.put("twohr/e/keyframes", b"e's keyframes")
        f.put("twohr/e/keyframes", b"f forging e's keyframes")
        p.put("twohr/p/keyframes", b"p tracks on the stack: its tracker sends them")
        e.put("twohr/maps/lab/merged", b"e announcing its own merge")
        mapserver.put("twohr/maps/lab/merged", b"e merged")
        asked = {name: [r.ok.payload.to_bytes() for r in session.get(replica_query(robot, "rpc/detect", "d1"),
                                                                     timeout=2.0) if r.ok is not None]
                 for name, session, robot in (("e", e, "e"), ("e for f", e, "f"), ("p", p, "p"))}
        # the map store takes a save without a session as the operator's: no robot may ask for one
        asked["e saves"] = [r.ok.payload.to_bytes() for r in e.get("twohr/maps/lab/save", payload=b"map",
                                                                     timeout=2.0) if r.ok is not None]
        time.sleep(1.0)
        assert sorted(results) == [("twohr/e/pose", b"e's pose"), ("twohr/e/status", b"e's status"),
                                   ("twohr/f/pose", b"f's pose")], results
        assert trackers == [edge_replica("e")], trackers  # once: f's token for e and p's own never reach it
        assert controls == {"e": [b"start"], "f": []}, controls
        assert shared == [("twohr/e/keyframes", b"e's keyframes")], shared
        # e hears the map server's merge; its own put reaches no one else (its session delivers it to itself alone)
        assert merges["gateway"] == [b"e merged"] and b"e merged" in merges["e"], merges
        assert asked == {"e": [b"kp"], "e for f": [], "p": [], "e saves": []}, asked
        assert replicas_seen == {"e": ["twohr/_alive/detector/d1"], "p": []}, replicas_seen
        for token in [*tokens, detector_token]:
            token.undeclare()
    finally:
        for session in sessions:
            session.close()
        router.close()


def test_a_robots_own_tracker_says_when_its_server_stages_go_and_come_back(zenoh_router, dev_sequence, caplog):
    """The own tracker composed in this process (the stack's ``TrackerService`` with the camera's inlet and the edge's
    stages), its three server stages stand-ins that hold their tokens and refuse every job: the detector's token goes
    while the camera's frames come (said on the console), and comes back (said on the session's status)."""
    import logging

    from twohr import keys
    from twohr.bus import BusConfig
    from twohr.config import PipelineConfig
    from twohr.messages import ControlMsg, encode
    from twohr_app.commands.camera import replay_payloads
    from twohr_app.edge import EdgeTracker

    bus = BusConfig(connect=[zenoh_router])
    stand_in = open_session(bus)
    names = ("detector", "yolo", "matcher")
    refusing = [stand_in.declare_queryable(f"twohr/*/{query}/stand-in", lambda q: q.reply_err(b"a stand-in"))
                for query in (keys.DETECT_QUERY, keys.DYNAMICS_QUERY, keys.MATCH_QUERY)]
    tokens = {name: stand_in.liveliness().declare_token(keys.alive_key(name, "stand-in")) for name in names}
    statuses: list[StatusMsg] = []
    listener = stand_in.declare_subscriber("twohr/r7/status", lambda s: statuses.append(
        decode(s.payload.to_bytes(), StatusMsg)[0]))
    tracker = EdgeTracker(bus, "r7", names)
    stop = threading.Event()
    thread = threading.Thread(target=tracker.service.run, args=(stop,), daemon=True)
    thread.start()
    frames = replay_payloads(str(dev_sequence), "r7", 0, 40, 0)
    caplog.set_level(logging.INFO, logger="twohr.edge")
    try:
        assert tracker.service.ready.wait(30)
        stand_in.put(keys.key("r7", keys.CONTROL), encode(ControlMsg(
            session_id="s7", robot_id="r7", frame_index=-1, stamp=time.time(), command="start",
            config=PipelineConfig(), tracker=tracker.replica)))
        deadline = time.monotonic() + 30
        while tracker.camera.served is None:
            assert time.monotonic() < deadline, "the session never came to the robot's own tracker"
            time.sleep(0.05)
        assert tracker.feed(next(frames)) and "out of reach" not in caplog.text
        tokens.pop("detector").undeclare()
        while tracker.stages.replicas["detector"].alive():
            assert time.monotonic() < deadline, "the detector's token never went"
            time.sleep(0.05)
        assert tracker.feed(next(frames))
        assert "the stack is out of reach: tracking in the local map, no new keyframes from its detector, yolo, " \
               "matcher until the link is back" in caplog.text
        assert not [s for s in statuses if s.state == "online"]
        tokens["detector"] = stand_in.liveliness().declare_token(keys.alive_key("detector", "stand-in"))
        while not tracker.stages.replicas["detector"].alive():
            assert time.monotonic() < deadline, "the detector's token never came back"
            time.sleep(0.05)
        assert tracker.feed(next(frames))
        while not (online := [s for s in statuses if s.state == "online"]):
            assert time.monotonic() < deadline, "the session's status never said the stack was back"
            time.sleep(0.05)
        assert online[0].service == "tracker" and online[0].session_id == "s7"
        assert online[0].detail.startswith("the stack was out of reach for ") and online[0].detail.endswith(
            "keyframes from its detector, yolo, matcher again"), online[0].detail
        tracker.end_sessions(timeout=30)
        assert not tracker.service.sessions and tracker.camera.served is None
        assert tracker.upstream_bytes() >= tracker.service.published_bytes > 0
    finally:
        stop.set()
        thread.join(timeout=60)
        listener.undeclare()
        for queryable in refusing:
            queryable.undeclare()
        for token in tokens.values():
            token.undeclare()
        stand_in.close()
