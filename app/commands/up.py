"""``twohr up``: the router, every service and the gateway as local processes, until Ctrl-C.

Secure by default: the router listens on loopback unless told otherwise, admits only the users ``twohr up``
generated for its own processes (one per role, passwords in a private folder that is removed at exit), and
enforces each role's access-control list (``twohr_app.access``). The HTTP API serves this host only (``--host``
on loopback) unless the stack runs on a fleet's keys (HTTPS, and the operator's token) or ``--insecure``; a bearer
token (``--api-token``) guards it on request.
Outside clients (camera drivers, other robots, ROS 2 nodes) join with the client config that
``--write-client-config`` writes. ``docker-compose.yml`` mirrors the same topology.

A fleet across hosts: ``--keys DIR`` (``twohr keys init DIR``) with ``--router tls/HOST:PORT`` runs every link on
mutual TLS, each process with its own certificate of the fleet's CA, each robot with its own identity (it may
publish only its own camera), the gateway on HTTPS; ``twohr keys revoke DIR ROBOT`` shuts a robot out while the
stack runs. It needs no ``DIR/ca.key`` (keep that offline): the router and the gateway serve the hosts their
certificates name (``keys init --host``, ``keys add-host``; ``0.0.0.0`` serves them all), and the operator's API
token is ``DIR/operator.token``. Listening beyond loopback without TLS is refused unless ``--insecure``.

Replicas: ``--replicas detector=2`` runs two detector processes; the tracker sends each keyframe job to one of
them (the least busy) and, if that one dies, again to another. ``--replicas tracker=2`` runs two trackers; the
gateway gives each session to one, the one whose sessions ask least of it, and a tracker that dies fails its
sessions alone. ``twohr up --join tls/STACK:7447 --only
detector,yolo --keys DIR`` runs replicas on another host that join a running stack's router, each with its own
service certificate (DIR holds ``services/<role>/`` for each: ``twohr keys add-service KEYS ROLE HOST --out DIR``
gives that host certificates of its own, ``ROLE@HOST``, revoked as a robot is); ``twohr health`` lists every
replica and its host.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from pathlib import Path

from twohr.keys import PIPELINE_SERVICES

from ..access import is_loopback
from ..supervisor import start_system


def check_exposure(args: argparse.Namespace) -> None:
    """Refuse to listen beyond loopback without TLS unless ``--insecure``: passwords, frames and poses would
    cross the network in clear text."""
    from twohr.errors import TwohrError

    if args.insecure or args.keys:
        return
    if not args.router.startswith("tls/") and not is_loopback(args.router):
        raise TwohrError(f"--router {args.router} is reachable from other hosts without TLS: passwords and frames "
                         "would cross the network in clear; give --keys DIR and a tls/ endpoint (twohr keys init), "
                         "or --insecure for a closed test network")
    if not is_loopback(args.host):
        raise TwohrError(f"--host {args.host} serves the HTTP API beyond this host without TLS: give --keys DIR "
                         "(HTTPS with a certificate of the fleet's CA), or --insecure for a closed test network")
    if args.router.startswith("tls/"):
        raise TwohrError(f"--router {args.router}: a tls/ endpoint needs the fleet's keys (--keys DIR)")


def parse_replicas(values: list[str] | None) -> dict[str, int]:
    """``["detector=2", "yolo=2,matcher=3"]`` as counts; one clear error for anything else."""
    from twohr.errors import ConfigError

    counts: dict[str, int] = {}
    for item in (part.strip() for value in values or [] for part in value.split(",")):
        name, _, count = item.partition("=")
        if not count.strip().lstrip("-").isdigit():
            raise ConfigError(f"--replicas {item!r}: write SERVICE=COUNT, e.g. detector=2")
        counts[name.strip()] = int(count)
    return counts


def _join(args: argparse.Namespace) -> int:
    """``--join``: replicas of network services on this host, joined to a running stack, until Ctrl-C."""
    from twohr.errors import ConfigError, TwohrError

    from ..supervisor import check_replicas, join_stack

    only = [name.strip() for name in (args.only or "").split(",") if name.strip()]
    if not only:
        raise ConfigError("--join needs --only SERVICE[,SERVICE]: the network services to run here (detector, yolo, "
                          "matcher)")
    counts = check_replicas({name: 1 for name in only} | parse_replicas(args.replicas), trackers=False)
    if extra := sorted(set(counts) - set(only)):
        raise ConfigError(f"--replicas names {', '.join(extra)}, which --only does not run here")
    if not args.keys and not args.insecure:
        raise ConfigError(f"--join {args.join}: give the fleet's keys (--keys DIR with services/<role>/ for "
                          f"{', '.join(only)}), or --insecure for a stack that admits anyone")
    t0 = time.monotonic()
    try:
        system = join_stack(args.join, counts, args.keys, args.timeout)
    except (TimeoutError, RuntimeError) as exc:
        raise TwohrError(str(exc)) from None
    print(f"joined {args.join} in {time.monotonic() - t0:.1f} s: replicas "
          + ", ".join(sorted(r for started in system.replicas.values() for r in started)) + "; Ctrl-C stops them",
          flush=True)
    return _run_until_stopped(system)


def _run_until_stopped(system) -> int:
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        stop.wait()
    finally:
        print("stopping …", flush=True)
        system.stop()
    return 0


def _check_keys(args: argparse.Namespace):
    """The fleet's keys of ``--keys``, checked before anything starts (one line: a host their certificates do not
    name, an ``--api-token`` beside them); a note when the CA's private key is on this host, where it is not
    needed."""
    from ..fleet import Fleet
    from ..supervisor import check_custody

    fleet = Fleet(args.keys)
    check_custody(fleet, args.router, [args.host], args.api_token)
    if (fleet.folder / "ca.key").exists():
        print(f"note: {fleet.folder / 'ca.key'} is on this host, where the stack does not need it (every process "
              "of it runs as you): keep it offline, and bring it back only to add a robot, host or replica",
              file=sys.stderr, flush=True)
    return fleet


def _check_args(args: argparse.Namespace) -> tuple[dict[str, int], float, int]:
    """What ``twohr up`` is told, checked before anything starts, one line for anything wrong: ``(replicas,
    max_robots, map_versions)``."""
    from twohr.errors import ConfigError
    from twohr_services.gateway.admission import parse_max_robots

    from ..supervisor import check_replicas
    from .maps import parse_map_versions

    if args.only:
        raise ConfigError("--only names the services a --join host runs; a stack runs every service")
    replicas = check_replicas(parse_replicas(args.replicas))
    max_robots = None if args.max_robots == "auto" else parse_max_robots(args.max_robots)
    map_versions = parse_map_versions(args.map_versions)
    check_exposure(args)
    if max_robots is None:  # measured on this host (kept after the first time), not assumed from its cores
        from ..capacity import auto_capacity

        capacity = auto_capacity(say=lambda line: print(line, flush=True))
        print(f"--max-robots auto: {capacity.line()}", flush=True)
        max_robots = capacity.robots
    return replicas, max_robots, map_versions


def _start(args: argparse.Namespace, replicas: dict[str, int], max_robots: float, map_versions: int):
    """Start the stack (on a fleet's keys, the denial log first: it takes over the router's output); one line if
    it does not come up."""
    from twohr.errors import TwohrError

    print(f"starting router on {args.router} and services {', '.join(PIPELINE_SERVICES)} + gateway …", flush=True)
    if args.keys:
        from ..fleet_router import DenialLog

        DenialLog().start()
    try:
        # the API token is --api-token's or none: on loopback the gateway serves this host's users, and beyond it
        # check_exposure asked for --keys (the operator's token, read from the keys folder) or --insecure
        return start_system(args.router, args.data_root or [str(Path.cwd())], args.recordings, args.host,
                            args.port, args.api_token, args.timeout, secure=not args.insecure,
                            ros2_domain=args.ros2_domain, foxglove_port=args.foxglove_port or None,
                            record_descriptors=args.record_descriptors, maps=args.maps, keys=args.keys,
                            replicas=replicas, max_robots=max_robots, map_versions=map_versions)
    except (TimeoutError, RuntimeError) as exc:
        raise TwohrError(str(exc)) from None


def _view_host(args: argparse.Namespace, fleet) -> tuple[str, str]:
    """``(host, note)``: where a client reaches the gateway and the live view, and a note for the gateway's URL. On
    a fleet's keys and a wildcard ``--host``, a client verifies the certificate, so the host is one of the names
    it holds, and the note lists them."""
    from ..fleet import LOCAL_NAMES, WILDCARDS

    if fleet is None or args.host.strip("[]") not in WILDCARDS:
        return args.host, ""
    served = fleet.served("gateway")
    return next((name for name in served if name not in LOCAL_NAMES), served[0]), \
        f" (as {', '.join(served)}: the names its certificate holds)"


def _print_access(args: argparse.Namespace, fleet, system, view_host: str) -> None:
    """How clients reach the running stack: robots' bundles or the client config, the live view."""
    from ..fleet import write_client_config
    from ..supervisor import gateway_url

    if args.insecure:
        print("WARNING: --insecure: the bus admits anyone who reaches it and the HTTP API has no token",
              file=sys.stderr, flush=True)
    if fleet is not None:
        print(f"fleet keys {args.keys}: robots join with their bundle (twohr keys add {args.keys} ROBOT --out "
              f"ROBOT.bundle --endpoint {args.router}); HTTPS verified with {Path(args.keys) / 'ca.crt'}; the "
              f"operator's API token is in {fleet.operator_token}", flush=True)
    elif not args.insecure:
        client_config = write_client_config(Path(args.write_client_config), args.router, system.credentials)
        print(f"Zenoh client config for outside clients: {client_config}", flush=True)
    if not args.foxglove_port:
        return
    from twohr.foxglove_live import view_url, ws_url

    if args.keys:  # TLS and a token (the placeholder: a token never goes to the terminal)
        url = gateway_url(view_host, args.port, fleet)
        print(f"live view: {ws_url(view_host, args.foxglove_port)} with TOKEN the view token of the operator's "
              f"API token (every robot) or a robot's (its own): GET {url}/live with the API token as Bearer "
              f"gives it (the API token itself never goes into a Foxglove URL); TLS verified with "
              f"{Path(args.keys) / 'ca.crt'}; in Foxglove: {view_url(view_host, args.foxglove_port, tls=True)}",
              flush=True)
    else:
        print(f"live view: {view_url(args.host, args.foxglove_port)}", flush=True)


def _up(args: argparse.Namespace) -> int:
    from ..supervisor import gateway_url

    if args.join:
        return _join(args)
    replicas, max_robots, map_versions = _check_args(args)
    fleet = _check_keys(args) if args.keys else None
    t0 = time.monotonic()
    system = _start(args, replicas, max_robots, map_versions)
    view_host, note = _view_host(args, fleet)
    print(f"all healthy in {time.monotonic() - t0:.1f} s — gateway {gateway_url(args.host, args.port, fleet)}{note} "
          f"(docs at /docs); poses on twohr/<robot>/pose; admits {max_robots:g} robots at 30 Hz (--max-robots); "
          "Ctrl-C stops everything", flush=True)
    _print_access(args, fleet, system, view_host)
    return _run_until_stopped(system)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("up", help="start the router, every service and the gateway as local processes",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--router", default="tcp/127.0.0.1:7447", help="endpoint the Zenoh router listens on (with "
                   "--keys a tls/HOST:PORT one; without, loopback only unless --insecure)")
    p.add_argument("--data-root", action="append", help="folder sequences may come from (repeatable; default .)")
    p.add_argument("--recordings", default="recordings", help="folder for MCAP recordings")
    p.add_argument("--maps", default=None, metavar="DIR", help="the map store: sessions build, localize in and "
                   "extend the maps in this folder (POST /sessions with \"map\", GET /maps; served on "
                   "twohr/maps/<name>); kept across restarts")
    p.add_argument("--map-versions", default=10, metavar="N", help="versions of each map the store keeps "
                   "(default 10): past it the oldest go, the others keep their numbers")
    p.add_argument("--host", default="127.0.0.1", help="gateway host")
    p.add_argument("--port", type=int, default=8080, help="gateway port")
    p.add_argument("--api-token", default=None, help="bearer token the HTTP API requires (default none: a "
                   "loopback --host serves this host's users only; beyond it give --keys, whose operator's token is "
                   "DIR/operator.token, and no --api-token)")
    p.add_argument("--write-client-config", default="runs/up/zenoh-client.json5", metavar="FILE",
                   help="where to write the Zenoh client config (router endpoint and credentials) that outside "
                   "clients, camera drivers and ROS 2 nodes use (default: %(default)s, private to you)")
    p.add_argument("--ros2-domain", type=int, default=None, metavar="ID",
                   help="also run the ros2 service: poses as ROS 2 topics (PoseStamped, Odometry, tf, Path) over "
                   "rmw_zenoh in this domain, which ROS 2 nodes with the client config can read")
    p.add_argument("--keys", default=None, metavar="DIR", help="a fleet's keys (twohr keys init DIR): every link "
                   "mutual TLS with one certificate per process, one identity per robot, revocation while running "
                   "(twohr keys revoke), the gateway on HTTPS; needed for a --router other hosts can reach. Runs "
                   "without DIR/ca.key, on the hosts the keys name (twohr keys add-host)")
    p.add_argument("--insecure", action="store_true", help="no bus authentication, access control or API token "
                   "(local experiments only)")
    p.add_argument("--foxglove-port", type=int, default=8765,
                   help="Foxglove WebSocket live view on the gateway host (default 8765; 0 turns it off); with "
                   "--keys on TLS, and a viewer needs ?token= in its URL: the operator's token sees every robot, a "
                   "robot's its own and the others' poses")
    p.add_argument("--record-descriptors", action="store_true",
                   help="keep the raw keypoint descriptors in every recording (large)")
    p.add_argument("--replicas", action="append", metavar="SERVICE=N", help="run N processes of a network service "
                   "(detector, yolo, matcher; repeatable or comma-separated, e.g. detector=2,yolo=2); each keyframe "
                   "job goes to one, the least busy, and again to another if it dies. tracker=N runs N trackers "
                   "(default: one per --max-robots): each session goes to one, the least loaded, and to another, with "
                   "its map, if it dies")
    p.add_argument("--max-robots", default="auto", metavar="N", help="robots the stack admits at 30 Hz, each on a "
                   "tracker of its own (N trackers run); past it POST /sessions gets 503 with Retry-After (a session "
                   "at \"rate\" 15 counts half); auto (default) = measured: the robots twohr bench --fleet carried on "
                   "this host, else one keyframe job and one frame timed at the first start (kept per CPU in "
                   "~/.cache/twohr/capacity.json)")
    p.add_argument("--join", default=None, metavar="ENDPOINT", help="run no stack: start replicas of the --only "
                   "services on this host, joined to the running stack's router at ENDPOINT (tls/HOST:7447 with "
                   "--keys)")
    p.add_argument("--only", default=None, metavar="SERVICES", help="with --join: the network services to run "
                   "here, comma-separated (e.g. detector,yolo)")
    p.add_argument("--timeout", type=float, default=120.0, help="seconds to wait for every service to be healthy")
    p.set_defaults(func=_up)
