"""The real compose stack in containers: the fleet's keys made on first start (one key folder per container), up,
healthy, a session on 60 real frames, every pose seen from outside by a robot with its own bundle over TLS, the MCAP
read back from the mounted folder over HTTPS; a map built by a session that outlives the stack going
down and up again; then down with nothing left running.

Run by ``make compose-test`` (scripts/docker-here.sh provides the engine, the image and
$TWOHR_COMPOSE); skipped in ``make test``.
"""

import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
from websockets.exceptions import InvalidStatus

from conftest import REPO
from twohr.bus import BusConfig, free_port, open_session
from twohr.errors import TwohrError
from twohr.foxglove_live import FoxgloveClient
from twohr.identity import load_identity
from twohr.keys import PIPELINE_SERVICES
from twohr_lab.bench.steps.bus_sessions import latency_summary, session_latency
from twohr_services.recorder.core import topic_counts

COMPOSE = os.environ.get("TWOHR_COMPOSE")
pytestmark = pytest.mark.skipif(not COMPOSE, reason="needs a Docker engine: run `make compose-test`")

FRAMES = 60
TOKEN = "compose-test-token"
PROJECT = f"twohr-test-{os.getpid()}"
SERVICES = ["router", *PIPELINE_SERVICES, "gateway"]
KEYS: dict[str, Path] = {}  # "dir": the fleet's keys the stack made


def compose(*args: str, env: dict, timeout: float = 600) -> subprocess.CompletedProcess:
    command = [*shlex.split(COMPOSE), "-p", PROJECT, *args]
    result = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout)
    assert result.returncode == 0, f"{' '.join(command)} failed:\n{result.stdout}\n{result.stderr}"
    return result


def project_containers() -> list[str]:
    result = subprocess.run(["docker", "ps", "-a", "-q", "--filter", f"label=com.docker.compose.project={PROJECT}"],
                            capture_output=True, text=True, check=True)
    return result.stdout.split()


def health(container: str) -> str:
    result = subprocess.run(["docker", "inspect", "--format", "{{.State.Health.Status}}", container],
                            capture_output=True, text=True)
    return result.stdout.strip() or result.stderr.strip()


def up_and_healthy(env: dict) -> None:
    """``docker compose up -d`` and wait until every service reports healthy."""
    compose("up", "-d", "--no-build", env=env)
    containers = {s: compose("ps", "-q", s, env=env).stdout.strip() for s in SERVICES}
    deadline = time.time() + 300
    while set((states := {s: health(c) for s, c in containers.items()}).values()) != {"healthy"}:
        assert "unhealthy" not in states.values(), states
        assert time.time() < deadline, f"not healthy after 300 s: {states}"
        time.sleep(1)


def wait_for_every_service(gateway: str, env: dict, restarted: bool = True, timeout: float = 120) -> None:
    """Until the gateway sees every service's liveliness token (``restarted``: first, until the router has
    restarted with the robots' new list, as ``twohr keys add`` on a running stack makes it)."""
    deadline = time.time() + timeout
    while restarted and "router restarted" not in compose("logs", "router", env=env).stdout:
        assert time.time() < deadline, "the router did not take the new robot"
        time.sleep(0.5)
    with https(gateway) as client:
        while (missing := client.get("/healthz").json()["missing_services"]):
            assert time.time() < deadline, f"services not back after the router's restart: {missing}"
            time.sleep(0.5)


def https(gateway: str, timeout: float = 60) -> httpx.Client:
    """The operator's HTTPS client of the gateway, verified with the fleet's CA."""
    return httpx.Client(base_url=gateway, timeout=timeout, headers={"Authorization": f"Bearer {TOKEN}"},
                        verify=ca())


def ca():
    """The fleet's CA, as HTTPS clients verify the gateway with."""
    import ssl

    return ssl.create_default_context(cafile=str(KEYS["dir"] / "ca.crt"))


def run_session(gateway: str, body: dict, timeout: float = 900) -> dict:
    """``POST /sessions`` and wait until it ends; its final info."""
    with https(gateway) as client:
        response = client.post("/sessions", json=body)
        assert response.status_code == 201, response.text
        session_id = response.json()["id"]
        deadline = time.time() + timeout
        while (info := client.get(f"/sessions/{session_id}").json())["state"] in ("starting", "running"):
            assert time.time() < deadline, info
            time.sleep(0.5)
        return info


def map_names(gateway: str) -> list[str]:
    with https(gateway) as client:
        listing = client.get("/maps")
    assert listing.status_code == 200, listing.text
    return [entry["name"] for entry in listing.json()]


@pytest.fixture(scope="module")
def stack(tmp_path_factory, dev_sequence, model_mirror):
    recordings, maps = tmp_path_factory.mktemp("compose_recordings"), tmp_path_factory.mktemp("compose_maps")
    KEYS["dir"] = tmp_path_factory.mktemp("compose_keys") / "keys"
    for folder in (recordings, maps):
        if os.geteuid() == 0:
            os.chown(folder, 10001, 10001)  # the image's non-root user writes the recordings and maps
        else:
            folder.chmod(0o777)
    router_port, gateway_port, live_port = free_port(), free_port(), free_port()
    env = {**os.environ, "TWOHR_DATA": str(dev_sequence.parent), "TWOHR_MODELS": str(model_mirror),
           "TWOHR_RECORDINGS": str(recordings), "TWOHR_MAPS": str(maps), "TWOHR_ROUTER_PORT": str(router_port),
           "TWOHR_GATEWAY_PORT": str(gateway_port), "TWOHR_LIVE_PORT": str(live_port), "TWOHR_API_TOKEN": TOKEN,
           "TWOHR_KEYS": str(KEYS["dir"]),
           # docker-compose's 60 s default is short where creating a container copies the image (vfs)
           "COMPOSE_HTTP_TIMEOUT": os.environ.get("COMPOSE_HTTP_TIMEOUT", "600")}
    t0 = time.time()
    healthy = False
    try:
        up_and_healthy(env)
        healthy = True
        bundle = tmp_path_factory.mktemp("robot") / "compose.bundle"
        added = subprocess.run([str(Path(sys.executable).with_name("twohr")), "keys", "add", str(KEYS["dir"]),
                                "compose", "--out", str(bundle), "--endpoint", f"tls/127.0.0.1:{router_port}"],
                               capture_output=True, text=True, timeout=60)
        assert added.returncode == 0, added.stderr
        wait_for_every_service(f"https://127.0.0.1:{gateway_port}", env)  # the router restarted with the new robot
        yield {"router": f"tls/127.0.0.1:{router_port}", "gateway": f"https://127.0.0.1:{gateway_port}",
               "recordings": recordings, "maps": maps, "startup_s": time.time() - t0, "bundle": bundle, "env": env,
               "live": f"wss://127.0.0.1:{live_port}"}
    finally:
        if not healthy:
            print(compose("logs", "--tail", "40", env=env).stdout)
        compose("down", "-v", "--remove-orphans", env=env)
        assert project_containers() == [], "containers left after down"


def test_session_in_containers_streams_every_pose_and_records_mcap(stack, dev_sequence):
    # the stack is secured: no certificate, no bus; no token, no API; each container sees its own key alone
    with pytest.raises(TwohrError):
        open_session(BusConfig(connect=[stack["router"]], identity=None, user=None, password=None,
                               config_file=None)).close()
    assert httpx.get(f"{stack['gateway']}/sessions", timeout=30, verify=ca()).status_code == 401
    # the live view too: TLS with the fleet's certificate, and no channel without a token
    with pytest.raises(InvalidStatus) as refused:
        FoxgloveClient(stack["live"], cafile=KEYS["dir"] / "ca.crt")
    assert refused.value.response.status_code == 401
    viewer = FoxgloveClient(stack["live"], token=TOKEN, cafile=KEYS["dir"] / "ca.crt")
    seen = compose("exec", "-T", "tracker", "ls", "/run/twohr/keys", env=stack["env"]).stdout.split()
    assert sorted(seen) == ["ca.crt", "cert.pem", "key.pem", "password"], seen
    robot = BusConfig(connect=[stack["router"]], identity=load_identity(stack["bundle"]), user=None, password=None,
                      config_file=None)
    result = session_latency(robot, stack["gateway"], dev_sequence.name, FRAMES, record=True, robot_id="compose",
                             timeout=900, api_token=TOKEN, verify=ca())
    info = result["session"]
    assert info["state"] == "finished" and info["frames"] == FRAMES, info
    # the independent subscriber outside the containers saw every frame's pose, once
    assert sorted(result["frame_indices"]) == list(range(FRAMES))
    assert info["ate_rmse"] is not None and info["ate_rmse"] < 0.05, info  # a real trajectory, not a stub
    # the operator's viewer saw the robot's camera and poses live
    viewer.close()
    assert viewer.counts.get("/compose/camera/image", 0) > 0 and viewer.counts.get("/compose/pose", 0) > 0, \
        viewer.counts

    # the gateway serves the file once the recorder has finalised it; the same bytes are in the mounted folder
    with https(stack["gateway"]) as client:
        served = client.get(f"/sessions/{info['id']}/recording")
    assert served.status_code == 200, served.text
    mcap = stack["recordings"] / f"{info['id']}.mcap"
    assert mcap.is_file(), sorted(p.name for p in Path(stack["recordings"]).iterdir())
    assert mcap.read_bytes() == served.content
    counts = topic_counts(mcap)
    # every frame's image once (the lean recording: raw frames are left out) and every pose
    assert counts["/compose/camera/image"] == FRAMES and counts["/twohr/compose/pose"] == FRAMES, counts
    # the default, camera-rate schedule: 2HR keypoints and masks only where the tracker service asked for them
    assert 1 <= counts["/twohr/compose/keypoints"] < FRAMES / 2, counts
    assert 1 <= counts["/twohr/compose/dynamics"] < FRAMES, counts

    out = REPO / "runs" / "compose"
    out.mkdir(parents=True, exist_ok=True)
    (out / "session.json").write_text(json.dumps(
        {"startup_s": round(stack["startup_s"], 1), **latency_summary(result), "ate_rmse": info["ate_rmse"]},
        indent=2))


def test_a_map_outlives_the_stack_going_down_and_up(stack, dev_sequence):
    built = run_session(stack["gateway"], {"sequence": dev_sequence.name, "robot_id": "a", "max_frames": FRAMES,
                                           "map": {"name": "lab", "mode": "build"}})
    assert built["state"] == "finished" and built["frames"] == FRAMES, built
    deadline = time.time() + 60
    while "lab" not in map_names(stack["gateway"]):  # saved after the session's final path
        assert time.time() < deadline, "map lab not saved"
        time.sleep(1)
    assert (stack["maps"] / "lab.map").is_file()

    compose("down", "--remove-orphans", env=stack["env"])
    assert project_containers() == []
    up_and_healthy(stack["env"])
    wait_for_every_service(stack["gateway"], stack["env"], restarted=False)
    assert "lab" in map_names(stack["gateway"])
    found = run_session(stack["gateway"], {"sequence": dev_sequence.name, "robot_id": "b", "start": FRAMES,
                                           "max_frames": FRAMES, "map": {"name": "lab", "mode": "localize"}})
    assert found["state"] == "finished" and found["frames"] >= 0.9 * FRAMES, found
