"""A fleet across hosts: the stack on its own network namespace, robots ``a`` and ``b`` and an intruder each on
theirs, linked to the stack by veth pairs (addresses only inside the namespaces made here).

The stack runs as ``twohr up --keys K --router tls/0.0.0.0:7447`` (every link mutual TLS, one identity per robot);
``a`` streams the dev frames with its bundle, ``b`` reads a's poses with its own and tries to put frames into a's
session; the intruder tries with no certificate and with a self-signed one named ``a``. A packet capture on the
stack's link to ``a`` must hold no key expression, no password and no JPEG in clear text. Then ``a`` is revoked
while ``a`` and ``b`` both stream.

This file is also the program a host runs to listen (``python test_fleet_hosts.py listen ...``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

TWOHR = Path(sys.executable).with_name("twohr")
PORT, GATEWAY = 7447, 8443
# the stack's end of each host's link; "far" runs a detector replica that joins the stack
STACK = {"a": "10.214.1.1", "b": "10.214.2.1", "x": "10.214.3.1", "far": "10.214.4.1"}
HOST = {"a": "10.214.1.2", "b": "10.214.2.2", "x": "10.214.3.2", "far": "10.214.4.2"}
TOKEN = "operator-token-fleet-hosts"
FAST = json.dumps({"detector.input_scale": 0.5})


def _listen(args: argparse.Namespace) -> int:
    """Subscribe to ``--key`` with the ``--keys`` bundle and append one line per sample (its arrival time) to
    ``--out``."""
    from twohr.bus import bus_from_args, open_session

    session = open_session(bus_from_args(args))
    out = open(args.out, "a", buffering=1)
    session.declare_subscriber(args.key, lambda sample: out.write(f"{time.time():.3f} {sample.key_expr}\n"))
    print("listening", flush=True)
    while True:
        time.sleep(1)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(required=True)
    p = sub.add_parser("listen")
    p.add_argument("--keys", required=True)
    p.add_argument("--router", default=None)
    p.add_argument("--key", required=True)
    p.add_argument("--out", required=True)
    p.set_defaults(func=_listen)
    args = parser.parse_args(argv)
    return args.func(args)


def twohr(*args: str) -> list[str]:
    return [str(TWOHR), *args]


def arrivals(path: Path) -> list[float]:
    return [float(line.split()[0]) for line in path.read_text().splitlines()] if path.is_file() else []


@pytest.fixture(scope="module")
def fleet(tmp_path_factory, network, dev_sequence):
    tmp = tmp_path_factory.mktemp("fleet_hosts")
    net = network(tmp, ["stack", *HOST])
    keys = tmp / "K"
    try:
        net.make([("stack", STACK[h], h, HOST[h]) for h in HOST])
        made = subprocess.run(twohr("keys", "init", str(keys), *[f"--host={ip}" for ip in STACK.values()]),
                              capture_output=True, text=True, timeout=60, env=os.environ | {"TWOHR_API_TOKEN": TOKEN})
        assert made.returncode == 0, made.stderr
        for robot in ("a", "b"):
            added = subprocess.run(twohr("keys", "add", str(keys), robot, "--out", str(tmp / f"{robot}.bundle"),
                                         "--endpoint", f"tls/{STACK[robot]}:{PORT}"), capture_output=True, text=True)
            assert added.returncode == 0, added.stderr
        capture = net.start("stack", "tcpdump", "-i", net.devices[("stack", "a")], "-U", "-s", "0", "-w",
                            str(tmp / "a-link.pcap"))
        stack = net.start("stack", *twohr("up", "--keys", str(keys), "--router", f"tls/0.0.0.0:{PORT}", "--port",
                                           str(GATEWAY), "--foxglove-port", "0",
                                           "--max-robots", "4", "--data-root", str(dev_sequence.parent), "--recordings",
                                           str(tmp / "recordings")))
        stack.wait_for(lambda text: "all healthy" in text, 240)
        yield {"net": net, "tmp": tmp, "keys": keys, "stack": stack, "capture": capture}
    finally:
        net.close()


def api(fleet, method: str, path: str, token: str = TOKEN, **kwargs):
    """One HTTPS request to the gateway, from the stack's host, verified with the fleet's CA."""
    import ssl

    import httpx

    context = ssl.create_default_context(cafile=str(fleet["keys"] / "ca.crt"))
    with fleet["net"].inside("stack"), httpx.Client(base_url=f"https://127.0.0.1:{GATEWAY}", timeout=30,
                                                    verify=context,
                                                    headers={"Authorization": f"Bearer {token}"}) as http:
        return http.request(method, path, **kwargs)


def bundle_token(fleet, robot: str) -> str:
    return json.loads((fleet["tmp"] / f"{robot}.bundle").read_text())["api_token"]


def start_session(fleet, robot: str) -> str:
    created = api(fleet, "POST", "/sessions", token=bundle_token(fleet, robot),
                  json={"robot_id": robot, "source": "camera", "config": json.loads(FAST), "record": False})
    assert created.status_code == 201, created.text
    return created.json()["id"]


def camera(fleet, host: str, bundle: str, robot: str, frames: int, start: int = 0, sequence: Path | None = None,
           rate: float = 30.0):
    return fleet["net"].start(host, *twohr("camera", "--keys", str(fleet["tmp"] / f"{bundle}.bundle"), "--robot",
                                           robot, "--replay", str(sequence), "--frames", str(frames),
                                           "--start", str(start), "--rate", f"{rate:g}"))


def listen(fleet, host: str, bundle: str, key: str, name: str):
    out = fleet["tmp"] / f"{name}.txt"
    program = fleet["net"].start(host, sys.executable, __file__, "listen", "--keys",
                                 str(fleet["tmp"] / f"{bundle}.bundle"), "--key", key, "--out", str(out))
    program.first_line(60)
    return out


def session(fleet, session_id: str) -> dict:
    answer = api(fleet, "GET", f"/sessions/{session_id}")
    assert answer.status_code == 200, answer.text
    return answer.json()


def test_one_identity_per_robot_tls_on_the_wire_and_no_intruder(fleet, dev_sequence, self_signed_bundle, camera_hz):
    a_session = start_session(fleet, "a")
    try:
        identity_and_wire(fleet, dev_sequence, self_signed_bundle, camera_hz, a_session)
    finally:  # the robot is free for the next test whatever this one found
        api(fleet, "DELETE", f"/sessions/{a_session}", token=bundle_token(fleet, "a"))


def identity_and_wire(fleet, dev_sequence, self_signed_bundle, camera_hz: float, a_session: str) -> None:
    # b's token cannot start, read or stop a's session
    assert api(fleet, "POST", "/sessions", token=bundle_token(fleet, "b"),
               json={"robot_id": "a", "source": "camera"}).status_code == 403
    assert api(fleet, "GET", f"/sessions/{a_session}", token=bundle_token(fleet, "b")).status_code == 403
    poses_at_b = listen(fleet, "b", "b", "twohr/a/pose", "poses-at-b")
    a_cam = camera(fleet, "a", "a", "a", 150, sequence=dev_sequence, rate=camera_hz)
    b_cam = camera(fleet, "b", "b", "a", 60, start=300, sequence=dev_sequence,  # b's frames into a's session
                   rate=camera_hz)
    assert a_cam.wait(120 + 150 / camera_hz) == 0 and b_cam.wait(120) == 0, a_cam.output() + b_cam.output()
    time.sleep(3.0)
    info = session(fleet, a_session)
    # a's session got a's 150 frames and none of b's 60, and b read a's poses
    assert info["state"] == "running" and info["frames_sent"] == 150, info
    assert info["frames"] >= 135, info
    assert len(arrivals(poses_at_b)) >= 135
    fleet["stack"].wait_for(lambda text: "denied 'b' put on twohr/a/camera" in text, 10)

    # the intruder: no certificate at all, and a self-signed one named a
    evil = self_signed_bundle("a", fleet["tmp"] / "evil.bundle")
    for keys in ([], ["--keys", str(evil)]):
        tried = fleet["net"].run("x", *twohr("camera", *keys, "--router", f"tls/{STACK['x']}:{PORT}", "--robot",
                                             "a", "--replay", str(dev_sequence), "--frames", "5"), timeout=60)
        assert tried.returncode == 2 and "cannot join the Zenoh bus" in tried.stderr, tried.stderr
        assert "Traceback" not in tried.stderr

    # nothing in clear on the wire to a: no key expression, no password, no JPEG, no API token
    fleet["capture"].stop()
    wire = (fleet["tmp"] / "a-link.pcap").read_bytes()
    a = json.loads((fleet["tmp"] / "a.bundle").read_text())
    assert len(wire) > 2_000_000, len(wire)  # 150 frames went through here
    for secret in (b"twohr/", a["password"].encode(), bundle_token(fleet, "a").encode(), b"JFIF\x00"):
        assert secret not in wire, secret
    assert api(fleet, "DELETE", f"/sessions/{a_session}", token=bundle_token(fleet, "a")).status_code == 200


def test_a_revoked_robot_is_shut_out_while_the_others_go_on(fleet, dev_sequence):
    a_session, b_session = start_session(fleet, "a"), start_session(fleet, "b")
    poses_at_a = listen(fleet, "a", "a", "twohr/b/pose", "poses-at-a")
    a_cam = camera(fleet, "a", "a", "a", 450, sequence=dev_sequence)
    b_cam = camera(fleet, "b", "b", "b", 450, sequence=dev_sequence)
    time.sleep(5.0)
    revoked = subprocess.run(twohr("keys", "revoke", str(fleet["keys"]), "a"), capture_output=True, text=True)
    assert revoked.returncode == 0, revoked.stderr
    t_revoke = time.time()
    fleet["stack"].wait_for(lambda text: "revoked a; router restarted" in text, 10)
    applied = time.time() - t_revoke
    time.sleep(10.0 - (time.time() - t_revoke))
    sent_a, heard_a = session(fleet, a_session)["frames_sent"], len(arrivals(poses_at_a))
    assert b_cam.wait(60) == 0, b_cam.output()
    a_cam.wait(60)
    time.sleep(3.0)
    # within 10 s nothing of a's reaches the stack and a receives nothing
    a_info, b_info = session(fleet, a_session), session(fleet, b_session)
    assert a_info["frames_sent"] == sent_a and len(arrivals(poses_at_a)) == heard_a, (a_info, heard_a)
    assert heard_a > 0  # it did hear b's poses before
    # b's session goes on, losing at most 2 s of frames (60 at 30 Hz)
    assert b_info["state"] == "running" and b_info["frames_sent"] >= 450 - 60, (b_info["detail"], b_info)
    assert api(fleet, "GET", f"/sessions/{b_session}", token=bundle_token(fleet, "a")).status_code == 401
    print(f"revocation applied {applied:.1f} s after twohr keys revoke; b: {b_info['frames_sent']} of 450 frames "
          f"relayed, {b_info['frames']} posed; a: {a_info['frames_sent']} relayed before")


def test_a_detector_replica_on_another_host_joins_with_its_own_key_and_takes_jobs(fleet, dev_sequence):
    # the far host is given a certificate of its own (detector@far), not the fleet's keys
    added = subprocess.run(twohr("keys", "add-service", str(fleet["keys"]), "detector", "far", "--out",
                                 str(fleet["tmp"] / "far-keys")), capture_output=True, text=True, timeout=60)
    assert added.returncode == 0, added.stderr
    far = fleet["net"].start("far", *twohr("up", "--join", f"tls/{STACK['far']}:{PORT}", "--only", "detector",
                                          "--keys", str(fleet["tmp"] / "far-keys")))
    joined = far.wait_for(lambda text: "joined" in text, 120)
    replica = joined.split("replicas ", 1)[1].split(";", 1)[0].strip()
    before = api(fleet, "GET", "/healthz").json()["services"]["tracker"]["jobs"]["detector"]
    assert replica in before["alive"] and len(before["alive"]) == 2, before
    created = api(fleet, "POST", "/sessions", json={"sequence": dev_sequence.name, "robot_id": "replay1",
                                                    "rate": 1.0, "max_frames": 150, "record": False,
                                                    "config": json.loads(FAST)})
    assert created.status_code == 201, created.text
    deadline = time.monotonic() + 120
    while session(fleet, created.json()["id"])["state"] in ("starting", "running"):
        assert time.monotonic() < deadline
        time.sleep(0.5)
    after = api(fleet, "GET", "/healthz").json()["services"]
    jobs = after["tracker"]["jobs"]["detector"]
    far_jobs = jobs["answered"].get(replica, 0) - before["answered"].get(replica, 0)
    assert far_jobs > 0 and jobs["lost"] == before["lost"], jobs
    assert replica in [r["replica"] for r in after["detector"]["replicas"]]
    far.stop()


if __name__ == "__main__":
    sys.exit(main())
