"""Static checks of docker-compose.yml and the Dockerfiles: every command, module and path they name exists."""

import importlib.util
import re
from pathlib import Path

import yaml

from conftest import REPO
from twohr.keys import PIPELINE_SERVICES
from twohr_app.cli import build_parser

COMPOSE = yaml.safe_load((REPO / "docker-compose.yml").read_text())


def _check_command(command: list[str]) -> None:
    if command[:2] == ["python", "-m"]:
        spec = importlib.util.find_spec(command[2])
        assert spec is not None and spec.submodule_search_locations, command
        assert (Path(spec.submodule_search_locations[0]) / "__main__.py").is_file(), command
    elif command[:2] == ["python", "-c"]:
        compile(command[2], "healthcheck", "exec")
    elif command[0] == "twohr":
        build_parser().parse_args(command[1:])  # exits (fails the test) on an unknown subcommand or flag
    else:
        raise AssertionError(f"unexpected command {command}")


def test_compose_mirrors_the_topology():
    services = COMPOSE["services"]
    assert set(services) == {"keys", "router", *PIPELINE_SERVICES, "gateway"}
    for name, svc in services.items():
        _check_command(svc["command"])
        if name == "keys":
            continue  # one-shot: makes the keys and exits
        assert svc["healthcheck"]["test"][0] == "CMD"
        _check_command(svc["healthcheck"]["test"][1:])
        assert svc["environment"]["TWOHR_ZENOH_ROUTER"] == "tls/router:7447"
    assert services["keys"]["build"]["context"] == "."
    assert (REPO / "Dockerfile").is_file()


def test_every_container_mounts_only_its_own_key():
    """The one-shot keys service makes the fleet's keys on first start (and keeps them after); each container mounts
    only its own key folder, read-only, joins the bus over TLS with it, and waits for what it needs; the router
    listens on TLS only; the gateway serves HTTPS and knows the robots' tokens."""
    services = COMPOSE["services"]
    keys = services["keys"]
    assert keys["command"][:4] == ["twohr", "keys", "init", "/keys"] and "--if-absent" in keys["command"]
    assert keys["volumes"] == ["${TWOHR_KEYS:-./keys}:/keys"]
    assert "secrets" not in COMPOSE.get("volumes", {})
    for name in ["router", *PIPELINE_SERVICES, "gateway"]:
        svc = services[name]
        key_mounts = [v for v in svc["volumes"] if "keys" in v.split(":")[0] or "/run/twohr" in v]
        assert key_mounts == [f"${{TWOHR_KEYS:-./keys}}/services/{name}:/run/twohr/keys:ro"], (name, key_mounts)
        assert svc["environment"]["TWOHR_ZENOH_KEYS"] == "/run/twohr/keys"
        waits_for = ("keys", "service_completed_successfully") if name == "router" else ("router", "service_healthy")
        assert svc["depends_on"][waits_for[0]]["condition"] == waits_for[1], name
    assert services["router"]["command"][-2:] == ["--listen", "tls/0.0.0.0:7447"]
    command = services["gateway"]["command"]
    for flag, value in (("--api-token-file", "/run/twohr/keys/operator.token"), ("--tls-keys", "/run/twohr/keys"),
                        ("--robot-tokens", "/run/twohr/keys/tokens.json"), ("--maps", "/maps")):
        assert command[command.index(flag) + 1] == value, flag
    assert "https://" in services["gateway"]["healthcheck"]["test"][-1]
    # the live view runs beside the HTTPS gateway with its keys: on TLS, with a token (tests/test_live_view_security.py)
    assert command[command.index("--foxglove-port") + 1] == "8765" and "--tls-keys" in command
    assert any(v.endswith(":/maps") for v in services["gateway"]["volumes"])


def test_the_map_room_holds_the_map_store_beside_the_gateway():
    """The map server serves the store on the bus: the same /maps as the gateway's HTTP /maps, as the same user (the
    one the keys service hands its key folder to), the same audit trail, and the operator's grants from its own key
    folder (``twohr keys grant`` writes its copy there)."""
    services = COMPOSE["services"]
    room, gateway = services["mapserver"], services["gateway"]
    flags = {flag: room["command"][room["command"].index(flag) + 1] for flag in ("--maps", "--audit-log",
                                                                                 "--map-grants")}
    assert flags == {"--maps": "/maps", "--audit-log": gateway["command"][gateway["command"].index("--audit-log") + 1],
                     "--map-grants": "/run/twohr/keys/grants.json"}
    assert "${TWOHR_MAPS:-./maps}:/maps" in room["volumes"] and "${TWOHR_MAPS:-./maps}:/maps" in gateway["volumes"]
    assert room["user"] == gateway["user"] == "${TWOHR_UID:-10001}"
    keys = services["keys"]["command"]
    assert keys[keys.index("mapserver=${TWOHR_UID:-10001}") - 1] == "--owner"


def test_volumes_match_service_flags():
    services = COMPOSE["services"]
    mounts = {name: {re.sub(r"\$\{[^}]*\}", "HOST", v).split(":")[1] for v in svc.get("volumes", [])}
              for name, svc in services.items()}
    assert "/data" in mounts["source"] and "/data" in mounts["gateway"]
    assert "/recordings" in mounts["recorder"] and "/recordings" in mounts["gateway"]
    assert "/models" in mounts["detector"] and "/models" in mounts["yolo"] and "/models" in mounts["matcher"]
    assert services["source"]["command"][-2:] == ["--data-root", "/data"]
    assert services["recorder"]["command"][-2:] == ["--recordings", "/recordings"]


def test_each_service_has_a_dockerfile_with_a_real_command():
    for name in [*PIPELINE_SERVICES, "gateway"]:
        dockerfile = REPO / "services" / name / "Dockerfile"
        text = dockerfile.read_text()
        cmd = yaml.safe_load(re.search(r"^CMD (\[.*\])$", text, re.M).group(1))
        _check_command(cmd)
        assert f"twohr_services.{name}" in cmd


def test_project_dockerfile_copies_what_exists():
    text = (REPO / "Dockerfile").read_text()
    for line in re.findall(r"^COPY (?!--from)(.+)$", text, re.M):
        for src in line.split()[:-1]:
            assert Path(REPO / src).exists(), src
    assert "USER twohr" in text
    # the build context keeps only what the image needs (no .venv, runs or recordings)
    ignore = (REPO / ".dockerignore").read_text().split()
    assert ignore[ignore.index("*") + 1:][:4] == ["!pyproject.toml", "!README.md", "!shared/", "!services/"]


def test_override_files_publish_ports_or_use_the_host_network():
    """Ports live in the override file that `docker compose up` reads by itself; the host file replaces it,
    because compose cannot publish ports under network_mode: host."""
    ports = yaml.safe_load((REPO / "docker-compose.override.yml").read_text())["services"]
    # published on loopback unless TWOHR_*_BIND says otherwise
    assert ports == {"router": {"ports": ["${TWOHR_ROUTER_BIND:-127.0.0.1}:${TWOHR_ROUTER_PORT:-7447}:7447"]},
                     "gateway": {"ports": ["${TWOHR_GATEWAY_BIND:-127.0.0.1}:${TWOHR_GATEWAY_PORT:-8080}:8080",
                                           "${TWOHR_GATEWAY_BIND:-127.0.0.1}:${TWOHR_LIVE_PORT:-8765}:8765"]}}
    assert all("ports" not in svc and "networks" not in svc for svc in COMPOSE["services"].values())

    host = yaml.safe_load((REPO / "docker-compose.host.yml").read_text())["services"]
    assert set(host) == set(COMPOSE["services"])
    router_endpoint = "tls/127.0.0.1:${TWOHR_ROUTER_PORT:-7447}"
    for name, svc in host.items():
        assert svc["network_mode"] == "host", name
        if name != "keys":
            assert svc["environment"]["TWOHR_ZENOH_ROUTER"] == router_endpoint, name
    assert host["keys"]["build"] == {"network": "host"}
    assert host["router"]["command"][-1].endswith(":${TWOHR_ROUTER_PORT:-7447}")
    assert host["router"]["healthcheck"]["test"][-2] == router_endpoint
    assert host["gateway"]["command"][host["gateway"]["command"].index("--port") + 1] == "${TWOHR_GATEWAY_PORT:-8080}"
    for svc in host.values():
        for command in (svc.get("command"), svc.get("healthcheck", {}).get("test", [None])[1:]):
            if command:
                _check_command(command)
    # a command the host file replaces keeps every option of the bridged one (the map store once went missing)
    for name, svc in host.items():
        if "command" in svc and "command" in COMPOSE["services"][name]:
            options = {token for token in COMPOSE["services"][name]["command"] if token.startswith("--")}
            assert options <= set(svc["command"]), (name, options - set(svc["command"]))
