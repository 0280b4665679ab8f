"""``twohr router``: a standalone Zenoh router.

- ``--secrets DIR``: the stack's router with per-role passwords (what the compose file's router ran before fleet
  keys; one shared ``client`` role for every outside client);
- ``--keys <keys>/services/router``: a fleet stack's router (what the compose file's router runs): mutual TLS,
  one identity per robot, revocation while running (:class:`~twohr_app.fleet_router.FleetRouter`);
- ``--keys ROBOT.bundle``: a robot's own router. The robot's processes join it on loopback with the same bundle
  (``--keys ROBOT.bundle --router tcp/127.0.0.1:7447``: Zenoh's password check, which a router that authenticates
  upstream also asks of its own clients), and it joins the stack's router (the bundle's endpoint, or ``--connect``)
  with the robot's identity, so the stack's per-robot rules hold for everything it forwards.
"""

from __future__ import annotations

import argparse
import os
import signal
import tempfile
import threading
from pathlib import Path


def router_secrets(folder: Path, api_token: str | None = None):
    """The credentials kept in ``folder``, made on first use: ``credentials.json`` and the router's
    ``users.txt``, one ``<role>.password`` per role and the gateway's ``api-token``, for containers that mount
    the folder (a volume only the stack's containers see)."""
    from ..access import Credentials

    path = folder / "credentials.json"
    if path.is_file():
        return Credentials.load(path)
    credentials = Credentials.generate(api_token)
    credentials.save(folder)
    for item in folder.iterdir():  # readable by the stack's other users (the recorder runs as the host's uid)
        item.chmod(0o644)
    folder.chmod(0o755)
    return credentials


def _serve(router, what: str) -> int:
    print(f"zenoh router {what}", flush=True)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait()
    router.close()
    return 0


def _fleet_router(args: argparse.Namespace) -> int:
    from twohr.bus import RouterSecurity, start_router
    from twohr.errors import TwohrError
    from twohr.identity import load_identity

    from ..access import is_loopback
    from ..fleet_router import DenialLog, FleetRouter

    keys = Path(args.keys)
    if (keys / "robots.json").is_file():  # the stack's router
        listen = args.listen or ["tls/0.0.0.0:7447"]
        if any(not endpoint.startswith("tls/") for endpoint in listen):
            raise TwohrError("a fleet's router listens on tls/ endpoints only")
        DenialLog().start()
        router = FleetRouter(keys, listen, args.ros2_domain)
        return _serve(router, f"listening on {', '.join(listen)} with the fleet keys in {keys} (robots "
                      f"{', '.join(router.robots) or 'none yet'})")
    identity = load_identity(keys)  # a robot's bundle: its own router
    listen = args.listen or ["tcp/127.0.0.1:7447"]
    exposed = [e for e in listen if not is_loopback(e)]
    if exposed and not args.insecure:
        raise TwohrError(f"--listen {exposed[0]}: a robot's router serves its own processes on loopback; other "
                         "hosts join the stack with bundles of their own (or give --insecure)")
    upstream = args.connect or identity.endpoint
    if not upstream:
        raise TwohrError(f"{keys} names no stack endpoint: give --connect tls/HOST:PORT")
    with tempfile.TemporaryDirectory(prefix="twohr-robot-router-") as private:
        users = Path(private) / "users.txt"  # the robot's own processes, with the robot's bundle
        users.write_text(f"{identity.name}:{identity.password.get_secret_value()}\n")
        router = start_router(listen, RouterSecurity(users_file=users), connect=[upstream], identity=identity)
        return _serve(router, f"of robot {identity.name} listening on {', '.join(listen)}, linked to {upstream}")


def _router(args: argparse.Namespace) -> int:
    from twohr.bus import RouterSecurity, start_router
    from twohr.errors import TwohrError

    from ..access import access_control, write_client_config

    if args.keys:
        return _fleet_router(args)
    listen = args.listen or ["tcp/0.0.0.0:7447"]
    security = None
    if not args.insecure:
        if args.secrets is None:
            raise TwohrError("give --secrets DIR (credentials are made there on first start) or --insecure")
        folder = Path(args.secrets)
        credentials = router_secrets(folder, os.environ.get("TWOHR_API_TOKEN"))
        security = RouterSecurity(users_file=folder / "users.txt", access_control=access_control(args.ros2_domain))
        write_client_config(folder / "client.json5", args.client_endpoint or listen[0], credentials).chmod(0o644)
    router = start_router(listen, security)
    return _serve(router, f"listening on {', '.join(listen)}" + (" (INSECURE)" if args.insecure else
                  f", users and access control from {args.secrets}"))


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("router", help="run a standalone Zenoh router: a stack's (what the compose file runs) or a "
                       "robot's own", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--listen", action="append", default=None, help="endpoint(s); default tcp/0.0.0.0:7447 (--secrets), "
                   "tls/0.0.0.0:7447 (a fleet's router), tcp/127.0.0.1:7447 (a robot's router)")
    p.add_argument("--keys", default=None, metavar="PATH", help="a fleet stack's router key folder "
                   "(<keys>/services/router), or a robot's bundle for the robot's own router (see above)")
    p.add_argument("--connect", default=None, metavar="tls/HOST:PORT", help="a robot's router: the stack's router "
                   "(default: the bundle's endpoint)")
    p.add_argument("--secrets", default=None, metavar="DIR", help="folder of the stack's credentials, made on first "
                   "start (per-role passwords, the API token, client.json5 for outside clients)")
    p.add_argument("--client-endpoint", default=None, help="router endpoint written into client.json5 (default: "
                   "the first --listen)")
    p.add_argument("--ros2-domain", type=int, default=0, help="ROS 2 domain whose rmw_zenoh keys clients may use")
    p.add_argument("--insecure", action="store_true", help="admit anyone, no access control")
    p.set_defaults(func=_router)
