"""The live view as guarded as the gateway: on a fleet's keys TLS and a token, checked before the WebSocket upgrade,
and each viewer shown what its token may see.

`twohr up --keys K` on loopback with robots `a` and `b`, during `a`'s session: a viewer with no token (or a wrong
one) is refused with 401 and gets no channel, a plain ws:// connection fails, `b`'s token gets a's poses and paths
but no channel of a's camera or map (not even by asking for every channel id), the operator's token gets every
channel, and `a`'s token a's camera. A view token (`GET /live` with an API token) opens the live view with its API
token's sight, and the HTTP API refuses it. Then, on the server alone with a fleet's real tokens file: a robot revoked
or expired while it watches is cut off, one robot cannot take the operator's seats, a token check that fails closes
that viewer and the checks go on, a subscription id past a u32 is a malformed request, and a viewer that stops
reading holds up neither the producer nor the other viewers. Last, `twohr bench --view-tls` (the TLS cost in
docs/live-view.md) on a few frames.
"""

from __future__ import annotations

import json
import os
import signal
import ssl
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus
from websockets.sync.client import connect

from conftest import read_until
from twohr.bus import free_port
from twohr.dataset import RGBDSequence
from twohr.foxglove_live import EVERYTHING, VIEWERS_PER_ROBOT, FoxgloveClient, LiveView, robot_viewer, sees_as_robot
from twohr_app.fleet import Fleet
from twohr_services.gateway.live import live_access
from twohr_services.gateway.settings import GatewaySettings
from twohr_services.gateway.tokens import view_token

FRAMES = 90
A_PRIVATE = ("/a/camera/image", "/a/camera/calibration", "/a/camera/keypoints", "/a/camera/dynamic_mask", "/a/map")
A_SHARED = ("/a/pose", "/a/path", "/a/keyframes", "/a/path_refined", "/tf")
OPERATOR_TOKEN = "operator-token-live-view"  # a gateway takes no token under 16 characters


def twohr(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "twohr_app", *args], capture_output=True, text=True, timeout=120)


def operator_token(keys: Path) -> str:
    """The operator's API token as `twohr keys init` wrote it."""
    for path in (keys / "operator.token", keys / "services" / "gateway" / "api-token"):
        if path.is_file():
            return path.read_text().strip()
    raise AssertionError(f"no operator token in {keys}")


def bundle_token(bundle: Path) -> str:
    return json.loads(bundle.read_text())["api_token"]


def wait_for(condition, timeout: float = 30.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


@pytest.fixture(scope="module")
def keyed_stack(tmp_path_factory, dev_sequence):
    """`twohr up --keys K` on loopback, robots a and b in K; the operator's token given as the environment."""
    tmp = tmp_path_factory.mktemp("live_keys")
    keys = tmp / "K"
    made = twohr("keys", "init", str(keys))
    assert made.returncode == 0, made.stderr
    for robot in ("a", "b"):
        added = twohr("keys", "add", str(keys), robot, "--out", str(tmp / f"{robot}.bundle"))
        assert added.returncode == 0, added.stderr
    operator = operator_token(keys)
    port, fox = free_port(), free_port()
    log = open(tmp / "up.log", "w")
    proc = subprocess.Popen(
        [sys.executable, "-m", "twohr_app", "up", "--keys", str(keys), "--router", f"tls/127.0.0.1:{free_port()}",
         "--port", str(port), "--foxglove-port", str(fox), "--data-root", str(dev_sequence.parent),
         "--recordings", str(tmp / "recordings"), "--max-robots", "2"],
        stdout=subprocess.PIPE, stderr=log, text=True, env=os.environ | {"TWOHR_API_TOKEN": operator})
    try:
        lines = read_until(proc, "live view:")
        if not lines[-1:] or not lines[-1].startswith("live view:"):
            pytest.fail("twohr up did not come up:\n" + "".join(lines) + (tmp / "up.log").read_text()[-3000:])
        yield {"tmp": tmp, "keys": keys, "operator": operator, "gateway": f"https://127.0.0.1:{port}",
               "fox": fox, "printed": "".join(lines), "tokens": {r: bundle_token(tmp / f"{r}.bundle") for r in "ab"}}
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()


def test_keyed_live_view_needs_tls_and_a_token_and_shows_each_robot_its_own(keyed_stack, dev_sequence):
    stack, ca = keyed_stack, keyed_stack["keys"] / "ca.crt"
    url = f"wss://127.0.0.1:{stack['fox']}"
    # the URL printed is wss:// with a placeholder: no token on the terminal
    assert f"live view: wss://127.0.0.1:{stack['fox']}/?token=TOKEN " in stack["printed"], stack["printed"]
    for secret in (stack["operator"], *stack["tokens"].values()):
        assert secret not in stack["printed"]

    # no token, a wrong one: refused before the upgrade, no channel
    for token in (None, "not-a-token", stack["tokens"]["a"] + "x"):
        with pytest.raises(InvalidStatus) as refused:
            FoxgloveClient(url, token=token, cafile=ca)
        assert refused.value.response.status_code == 401, token
    # a plain WebSocket on the live view's port, with a good token: no TLS, no answer (the server drops the plain
    # bytes; the client sees a bad handshake, a reset or a close, depending on timing)
    with pytest.raises((InvalidHandshake, ConnectionClosed, OSError)):
        connect(f"ws://127.0.0.1:{stack['fox']}/?token={stack['operator']}",
                subprotocols=["foxglove.websocket.v1"], open_timeout=10)
    # TLS with any other trust than the fleet's CA: refused by the client
    with pytest.raises(ssl.SSLCertVerificationError):
        FoxgloveClient(url, token=stack["operator"])

    viewers = {who: FoxgloveClient(url, token=token, cafile=ca)
               for who, token in (("operator", stack["operator"]), ("a", stack["tokens"]["a"]),
                                  ("b", stack["tokens"]["b"]))}
    sdk_named = FoxgloveClient(url, "foxglove.sdk.v1", token=stack["operator"], cafile=ca)
    context = ssl.create_default_context(cafile=str(ca))
    with httpx.Client(base_url=stack["gateway"], verify=context, timeout=30,
                      headers={"Authorization": f"Bearer {stack['tokens']['a']}"}) as http:
        created = http.post("/sessions", json={"sequence": dev_sequence.name, "robot_id": "a", "max_frames": FRAMES,
                                               "rate": 0.5, "record": False})
        assert created.status_code == 201, created.text
        session = created.json()["id"]
        wait_for(lambda: viewers["operator"].counts.get("/a/camera/image", 0) >= 5, 180, "a's first frames")
        # b asks for every channel by its id, advertised to it or not
        b = viewers["b"]
        for channel_id in range(1, 41):
            b.subscribe(channel_id)
        wait_for(lambda: http.get(f"/sessions/{session}").json()["state"] == "finished", 300, "a's session to end")
    time.sleep(1.0)

    operator, a = viewers["operator"], viewers["a"]
    print({who: dict(sorted(v.counts.items())) for who, v in viewers.items()})
    assert set(A_PRIVATE + A_SHARED) <= set(operator.topics())
    assert set(sdk_named.topics()) == set(operator.topics())
    assert operator.counts["/a/camera/image"] >= FRAMES // 2 and operator.counts["/a/map"] >= 1, operator.counts
    assert sdk_named.counts["/a/camera/image"] >= FRAMES // 2
    assert set(A_PRIVATE + A_SHARED) <= set(a.topics())
    assert a.counts["/a/camera/image"] >= FRAMES // 2 and a.counts["/a/pose"] >= FRAMES // 2, a.counts
    # b: a's poses and paths, none of a's camera, calibration, keypoints, masks or map points
    assert set(b.topics()) & set(A_PRIVATE) == set(), b.topics()
    assert {topic for topic in b.topics() if topic.startswith("/a/")} | {"/tf"} == set(A_SHARED)
    assert b.counts.get("/a/pose", 0) >= FRAMES // 2 and b.counts.get("/tf", 0) >= FRAMES // 2, b.counts
    assert all(b.counts.get(topic, 0) == 0 for topic in A_PRIVATE), b.counts
    assert not [topic for topic in b.counts if topic.startswith("?")], b.counts  # nothing by a channel id it guessed
    refused_ids = {int(s.rsplit(" ", 1)[1]) for s in b.statuses if s.startswith("Unknown channel ID")}
    private_ids = {c["id"] for c in operator.channels.values() if c["topic"] in A_PRIVATE}
    assert private_ids <= refused_ids, (private_ids, refused_ids)
    for viewer in (*viewers.values(), sdk_named):
        viewer.close()


def test_a_view_token_opens_the_live_view_and_nothing_of_the_api(keyed_stack):
    stack, ca = keyed_stack, keyed_stack["keys"] / "ca.crt"
    assert f"GET {stack['gateway']}/live with the API token" in stack["printed"], stack["printed"]
    bearer = lambda token: {"Authorization": f"Bearer {token}"}  # noqa: E731
    with httpx.Client(base_url=stack["gateway"], verify=ssl.create_default_context(cafile=str(ca)), timeout=30) as http:
        assert http.get("/live").json() == {"foxglove_port": stack["fox"], "tls": True}  # no token: no view token
        assert http.get("/live", headers=bearer("not-a-token-of-this-fleet")).status_code == 401
        views = {who: http.get("/live", headers=bearer(token)).json()["view_token"]
                 for who, token in (("operator", stack["operator"]), ("b", stack["tokens"]["b"]))}
        assert views == {"operator": view_token(stack["operator"]), "b": view_token(stack["tokens"]["b"])}
        for view in views.values():  # the HTTP API refuses a view token
            assert http.get("/sessions", headers=bearer(view)).status_code == 401
            assert http.get("/live", headers=bearer(view)).status_code == 401
    url = f"wss://127.0.0.1:{stack['fox']}"
    with pytest.raises(InvalidStatus) as refused:  # the view token of a token the gateway does not know
        FoxgloveClient(url, token=view_token("not-a-token-of-this-fleet"), cafile=ca)
    assert refused.value.response.status_code == 401
    operator, b = (FoxgloveClient(url, token=views[who], cafile=ca) for who in ("operator", "b"))
    wait_for(lambda: operator.server_info is not None and b.server_info is not None, 10, "both viewers admitted")
    time.sleep(0.5)
    # each sees what its API token sees (a's channels exist once the first test ran a's session)
    assert set(b.topics()) & set(A_PRIVATE) == set() and set(b.topics()) <= set(operator.topics())
    assert not b.closed and not operator.closed
    b.close()
    operator.close()


def test_topics_a_robot_sees():
    assert all(sees_as_robot("a", topic) for topic in (*A_PRIVATE, *A_SHARED, "/a/anything"))
    assert [t for t in A_PRIVATE if sees_as_robot("b", t)] == []
    assert all(sees_as_robot("b", t) for t in A_SHARED)
    assert not sees_as_robot("ab", "/a/pose/../camera/image") and not sees_as_robot("a", "/ab/camera/image")
    assert not sees_as_robot("b", "/a") and not sees_as_robot("b", "")


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    folder = tmp_path_factory.mktemp("live_fleet") / "K"
    fleet = Fleet(folder)
    fleet.init()
    bundles = {robot: fleet.add(robot, folder.parent / f"{robot}.bundle") for robot in ("a", "b")}
    return fleet, {robot: bundle.api_token.get_secret_value() for robot, bundle in bundles.items()}


def keyed_view(fleet: Fleet, operator: str) -> LiveView:
    gateway = fleet.service_folder("gateway")
    tls, authorize = live_access(GatewaySettings(tls_keys=gateway, robot_tokens=gateway / "tokens.json",
                                                 api_token=operator))
    return LiveView(port=0, tls=tls, authorize=authorize)


def test_a_revoked_robot_is_cut_off_the_live_view(fleet):
    fleet, tokens = fleet
    view = keyed_view(fleet, OPERATOR_TOKEN)
    ca = fleet.folder / "ca.crt"
    try:
        view.advertise("a")
        url = f"wss://127.0.0.1:{view.port}"
        a, operator = FoxgloveClient(url, token=tokens["a"], cafile=ca), FoxgloveClient(url, token=OPERATOR_TOKEN,
                                                                                        cafile=ca)
        wait_for(lambda: len(a.subscriptions) == len(view.channels) == len(operator.subscriptions), 10, "subscribed")
        time.sleep(0.3)
        view.log(view.converter.pose("a", 1.0, [0, 0, 0], [0, 0, 0, 1]))
        wait_for(lambda: a.counts.get("/a/pose") == 1 and operator.counts.get("/a/pose") == 1, 10, "a pose")
        fleet.revoke("a")
        t0 = time.monotonic()
        wait_for(lambda: a.closed, 5, "a's viewer to be closed")
        cut = time.monotonic() - t0
        view.log(view.converter.pose("a", 2.0, [1, 0, 0], [0, 0, 0, 1]))
        wait_for(lambda: operator.counts.get("/a/pose") == 2, 10, "the operator's second pose")
        assert a.counts["/a/pose"] == 1 and not operator.closed
        with pytest.raises(InvalidStatus) as refused:
            FoxgloveClient(url, token=tokens["a"], cafile=ca)
        assert refused.value.response.status_code == 401
        print(f"a revoked robot's viewer closed {cut:.2f} s after the tokens file changed")
        a.close()
        operator.close()
    finally:
        view.close()


def test_an_expired_robot_is_cut_off_the_live_view(fleet):
    """A robot whose certificate (and so its token) expires while it watches: closed at the next check, and refused
    from then on; the operator stays."""
    fleet, _ = fleet
    brief = fleet.add("brief", fleet.folder.parent / "brief.bundle", days=5 / 86400).api_token.get_secret_value()
    view = keyed_view(fleet, OPERATOR_TOKEN)
    ca = fleet.folder / "ca.crt"
    try:
        url = f"wss://127.0.0.1:{view.port}"
        watching = FoxgloveClient(url, token=view_token(brief), cafile=ca)
        operator = FoxgloveClient(url, token=view_token(OPERATOR_TOKEN), cafile=ca)
        wait_for(lambda: watching.closed, 20, "the expired robot's viewer to be closed")
        with pytest.raises(InvalidStatus) as refused:
            FoxgloveClient(url, token=brief, cafile=ca)
        assert refused.value.response.status_code == 401 and not operator.closed
        operator.close()
    finally:
        view.close()


def test_one_robot_cannot_take_the_operators_seats(fleet):
    fleet, tokens = fleet
    view = keyed_view(fleet, OPERATOR_TOKEN)
    ca = fleet.folder / "ca.crt"
    url = f"wss://127.0.0.1:{view.port}"
    try:
        mine = [FoxgloveClient(url, token=tokens["b"], cafile=ca) for _ in range(VIEWERS_PER_ROBOT)]
        for token in (tokens["b"], view_token(tokens["b"])):  # b's share is full, whichever of its tokens it shows
            with pytest.raises(InvalidStatus) as refused:
                FoxgloveClient(url, token=token, cafile=ca)
            assert refused.value.response.status_code == 503
        others = [FoxgloveClient(url, token=token, cafile=ca) for token in (OPERATOR_TOKEN, view_token(OPERATOR_TOKEN))]
        wait_for(lambda: all(c.server_info is not None for c in [*mine, *others]), 10, "every viewer admitted")
        assert len(view.clients) == VIEWERS_PER_ROBOT + 2
        for client in (*mine, *others):
            client.close()
    finally:
        view.close()


def test_a_failing_token_check_closes_that_viewer_and_the_checks_go_on(pose_view):
    view, valid, failing = pose_view
    url = f"ws://127.0.0.1:{view.port}"
    good, flaky, other = (FoxgloveClient(url, token=token) for token in ("good", "flaky", "other"))
    wait_for(lambda: all(c.server_info is not None for c in (good, flaky, other)), 10, "every viewer admitted")
    failing.add("flaky")  # its next check raises
    wait_for(lambda: flaky.closed, 10, "the viewer whose check failed to be closed")
    valid.discard("other")  # the checks went on: a token no longer valid is still seen
    wait_for(lambda: other.closed, 10, "the next refused viewer to be closed")
    assert not good.closed
    good.close()


def test_a_subscription_id_past_a_u32_is_a_malformed_request(pose_view):
    view, _, _ = pose_view
    client = FoxgloveClient(f"ws://127.0.0.1:{view.port}", token="good")
    wait_for(lambda: "/a/pose" in client.topics() and len(client.subscriptions) == len(view.channels), 10,
             "subscribed")
    pose = next(c["id"] for c in client.channels.values() if c["topic"] == "/a/pose")
    for bad in (2**32, -1, "1", 1.5):
        client.ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": bad, "channelId": pose}]}))
    wait_for(lambda: client.statuses.count("malformed request") == 4, 10, "four malformed requests")
    time.sleep(0.2)
    view.log(view.converter.pose("a", 1.0, [1, 0, 0], [0, 0, 0, 1]))  # the viewer's writer is still up
    wait_for(lambda: client.counts.get("/a/pose") == 1, 10, "the pose after the malformed requests")
    assert not client.closed
    client.close()


@pytest.fixture
def pose_view():
    """A live view with a token check of its own (no TLS): ``valid`` tokens see everything, a token in ``failing``
    makes the check raise; robot a's channels advertised."""
    valid, failing = {"good", "flaky", "other"}, set()

    def authorize(token: str):
        if token in failing:
            raise RuntimeError(f"the check of {token} failed")
        return EVERYTHING if token == "good" else robot_viewer(token) if token in valid else None

    view = LiveView(port=0, authorize=authorize)
    view.advertise("a")
    yield view, valid, failing
    view.close()


def test_a_viewer_that_stops_reading_holds_up_no_one(fleet, dev_sequence):
    fleet, tokens = fleet
    view = keyed_view(fleet, OPERATOR_TOKEN)
    ca = fleet.folder / "ca.crt"
    sequence = RGBDSequence(dev_sequence)
    images = [path.read_bytes() for path in (record.rgb_path for record in sequence.records[:20])]
    try:
        view.advertise("b")
        url = f"wss://127.0.0.1:{view.port}/?token={tokens['b']}"
        # a viewer that subscribes to everything and then reads nothing (its socket fills, the server's queue for it
        # drops its oldest messages)
        with connect(url, subprotocols=["foxglove.websocket.v1"], ssl=ssl.create_default_context(cafile=str(ca)),
                     max_queue=1, compression=None) as stalled:
            stalled.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": i, "channelId": i} for i in range(1, len(view.channels) + 1)]}))
            stalled_and_reader(view, stalled, ca, tokens["b"], sequence, images)
    finally:
        view.close()


def stalled_and_reader(view: LiveView, stalled, ca: Path, token: str, sequence: RGBDSequence, images: list[bytes]):
    """A reading viewer beside ``stalled``, while 400 frames are logged."""
    reader = FoxgloveClient(f"wss://127.0.0.1:{view.port}", token=token, cafile=ca)
    wait_for(lambda: len(reader.subscriptions) == len(view.channels), 10, "subscribed")
    time.sleep(0.5)
    frames = 400
    t0 = time.monotonic()
    for i in range(frames):
        view.log(view.converter.frame("b", float(i), sequence.camera, encoded=images[i % len(images)]))
        view.log(view.converter.pose("b", float(i), [0.01 * i, 0, 0], [0, 0, 0, 1]))
        if i % 10 == 0:
            time.sleep(0.05)  # about the rate the reader takes them in on a loaded machine
    logged = time.monotonic() - t0
    wait_for(lambda: reader.counts.get("/b/pose", 0) == frames, 60, "every pose at the reading viewer")
    stalled_client = next(c for c in list(view.clients) if
                          c.connection.remote_address[1] == stalled.local_address[1])
    print(f"{frames} frames ({sum(len(i) for i in images) // len(images) // 1000} kB images) logged in "
          f"{logged:.2f} s; the stalled viewer lost {stalled_client.dropped} messages, holding "
          f"{stalled_client.data_bytes / 1e6:.1f} MB")
    # the producer never waited on the stalled viewer; the reader got every message; the stalled one's queue is
    # bounded and lost its oldest
    assert logged < 40 * 0.05 + 5.0, logged
    assert reader.counts["/b/camera/image"] == frames and stalled_client.dropped > 0
    assert stalled_client.data_bytes <= 16 << 20
    assert np.isclose(reader.decode("/b/pose").pose.position.x, 0.01 * (frames - 1))
    reader.close()


def test_bench_view_tls_measures_both_links(dev_sequence, tmp_path):
    """`twohr bench --view-tls`: the figure in docs/live-view.md, here on a few frames."""
    out = tmp_path / "bench"
    done = subprocess.run([sys.executable, "-m", "twohr_app", "bench", "--view-tls", "--sequence", str(dev_sequence),
                           "--frames", "60", "--runs", "1", "--quiet", "--out", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    report = json.loads((out / "bench.json").read_text())["view_tls"]
    assert report["received"] == {"ws": [60], "wss": [60]}  # every frame reached the viewer on both
    assert report["fps_median"]["ws"] > 30 and report["fps_median"]["wss"] > 30, report
    camera = report["camera_rate"]
    assert camera["fps_median"]["wss"] == pytest.approx(30, rel=0.2)
    assert all(v > 0 for side in ("server", "viewer") for v in camera[f"{side}_cpu_ms_per_frame"].values())
    assert "FPS on wss:// with a token" in done.stdout
