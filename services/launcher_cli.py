"""``twohr up`` and ``twohr router``: the whole system as local processes, no containers needed.

``twohr up`` starts a Zenoh router inside its own process, then every service as a subprocess
(``python -m twohr_services.<name>``) and the HTTP gateway, waits until all answer their health
query, and stops everything cleanly on Ctrl-C (SIGINT, then SIGTERM, then SIGKILL after a grace).
``docker-compose.yml`` mirrors the same topology, one container per service.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

PIPELINE_SERVICES = ["source", "detector", "yolo", "matcher", "tracker", "recorder"]


class ProcessGroup:
    """Child processes that are stopped together, in reverse start order."""

    def __init__(self) -> None:
        self.procs: list[tuple[str, subprocess.Popen]] = []

    def start(self, name: str, args: list[str], env: dict[str, str]) -> subprocess.Popen:
        proc = subprocess.Popen([sys.executable, "-m", *args], env=env)
        self.procs.append((name, proc))
        return proc

    def dead(self) -> list[tuple[str, int]]:
        return [(name, proc.returncode) for name, proc in self.procs if proc.poll() is not None]

    def stop(self, grace: float = 10.0) -> None:
        for _, proc in reversed(self.procs):
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace
        for _, proc in self.procs:
            try:
                proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def _wait_http(url: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with urllib.request.urlopen(url, timeout=1) as response:
                if response.status == 200:
                    return
        except OSError:
            time.sleep(0.2)
    raise TimeoutError(f"gateway did not answer at {url} within {timeout:.0f} s")


def start_system(router: str, data_roots: list[str], recordings: str, host: str, port: int,
                 api_token: str | None = None, timeout: float = 120.0, log_level: str = "INFO",
                 foxglove_port: int | None = None, record_descriptors: bool = False):
    """Start the router, the services and the gateway; returns (router session, ProcessGroup) once healthy.
    ``foxglove_port`` turns on the gateway's Foxglove live view on ``host``."""
    from twohr.bus import BusConfig, open_session, start_router, wait_for_services

    router_session = start_router([router])
    env = dict(os.environ, TWOHR_ZENOH_ROUTER=router, TWOHR_LOG_LEVEL=log_level)
    group = ProcessGroup()
    try:
        roots = [arg for root in data_roots for arg in ("--data-root", root)]
        for name in PIPELINE_SERVICES:
            extra = {"source": roots, "recorder": ["--recordings", recordings] + (
                ["--record-descriptors"] if record_descriptors else [])}.get(name, [])
            group.start(name, [f"twohr_services.{name}", *extra], env)
        gateway_args = ["twohr_services.gateway", "--host", host, "--port", str(port), "--recordings", recordings,
                        *roots, "--foxglove-port", str(foxglove_port or 0)] + (
                            ["--api-token", api_token] if api_token else [])
        group.start("gateway", gateway_args, env)
        client = open_session(BusConfig(connect=[router]))
        try:
            wait_for_services(client, PIPELINE_SERVICES, timeout=timeout)
        finally:
            client.close()
        _wait_http(f"http://{host}:{port}/healthz", timeout)
        if group.dead():
            raise RuntimeError(f"processes exited during start-up: {group.dead()}")
    except BaseException:
        group.stop()
        router_session.close()
        raise
    return router_session, group


def _up(args: argparse.Namespace) -> int:
    from twohr.errors import TwohrError

    t0 = time.monotonic()
    print(f"starting router on {args.router} and services {', '.join(PIPELINE_SERVICES)} + gateway …", flush=True)
    try:
        router, group = start_system(args.router, args.data_root or [str(Path.cwd())], args.recordings, args.host,
                                     args.port, args.api_token, args.timeout, foxglove_port=args.foxglove_port or None,
                                     record_descriptors=args.record_descriptors)
    except (TimeoutError, RuntimeError) as exc:
        raise TwohrError(str(exc)) from None
    print(f"all healthy in {time.monotonic() - t0:.1f} s — gateway http://{args.host}:{args.port} "
          f"(docs at /docs); poses on twohr/<robot>/pose; Ctrl-C stops everything", flush=True)
    if args.foxglove_port:
        from twohr.foxglove_live import view_url

        print(f"live view: {view_url(args.host, args.foxglove_port)}", flush=True)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        while not stop.wait(1.0):
            dead = group.dead()
            if dead:
                print(f"twohr: a process exited: {dead}; stopping", file=sys.stderr)
                return 1
    finally:
        print("stopping …", flush=True)
        group.stop()
        router.close()
    return 0


def _router(args: argparse.Namespace) -> int:
    from twohr.bus import start_router

    listen = args.listen or ["tcp/0.0.0.0:7447"]
    router = start_router(listen)
    print(f"zenoh router listening on {', '.join(listen)}", flush=True)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait()
    router.close()
    return 0


def _health(args: argparse.Namespace) -> int:
    from twohr.bus import BusConfig, open_session, query_health

    session = open_session(BusConfig(connect=[args.router]) if args.router else BusConfig())
    try:
        if args.bus_only:
            print("bus ok")
            return 0
        names = args.names or PIPELINE_SERVICES
        answers = {name: query_health(session, name, timeout=args.timeout) for name in names}
    finally:
        session.close()
    for name, health in answers.items():
        print(f"{name:10} " + ("NOT ANSWERING" if health is None else
                               " ".join(f"{k}={v}" for k, v in health.items() if k != "service")))
    return 0 if all(h is not None for h in answers.values()) else 1


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("up", help="start the router, every service and the gateway as local processes",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--router", default="tcp/127.0.0.1:7447", help="endpoint the Zenoh router listens on")
    p.add_argument("--data-root", action="append", help="folder sequences may come from (repeatable; default .)")
    p.add_argument("--recordings", default="recordings", help="folder for MCAP recordings")
    p.add_argument("--host", default="127.0.0.1", help="gateway host")
    p.add_argument("--port", type=int, default=8080, help="gateway port")
    p.add_argument("--api-token", default=None, help="require this bearer token on /sessions")
    p.add_argument("--foxglove-port", type=int, default=8765,
                   help="Foxglove WebSocket live view on the gateway host (default 8765; 0 turns it off)")
    p.add_argument("--record-descriptors", action="store_true",
                   help="keep the raw keypoint descriptors in every recording (large)")
    p.add_argument("--timeout", type=float, default=120.0, help="seconds to wait for every service to be healthy")
    p.set_defaults(func=_up)

    p = sub.add_parser("health", help="ask services for their health counters over the bus (exit 1 if one is silent)")
    p.add_argument("names", nargs="*", help=f"services (default: {' '.join(PIPELINE_SERVICES)})")
    p.add_argument("--router", default=None, help="Zenoh router endpoint (default $TWOHR_ZENOH_ROUTER)")
    p.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for each answer")
    p.add_argument("--bus-only", action="store_true", help="only check that the router accepts a session")
    p.set_defaults(func=_health)

    p = sub.add_parser("router", help="run a standalone Zenoh router (what the compose file's router service runs)")
    p.add_argument("--listen", action="append", default=None, help="endpoint(s), default tcp/0.0.0.0:7447")
    p.set_defaults(func=_router)
