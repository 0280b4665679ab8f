"""``twohr router``: a standalone Zenoh router.

- ``--keys <keys>/services/router``: a fleet stack's router (what the compose file's router runs): mutual TLS,
  one identity per robot, revocation while running (:class:`~twohr_app.fleet_router.FleetRouter`);
- ``--keys ROBOT.bundle``: a robot's own router. The robot's processes join it on loopback with the same bundle
  (``--keys ROBOT.bundle --router tcp/127.0.0.1:7447``: Zenoh's password check, which a router that authenticates
  upstream also asks of its own clients), and it joins the stack's router (the bundle's endpoint, or ``--connect``)
  with the robot's identity, so the stack's per-robot rules hold for everything it forwards;
- ``--insecure``: a router that admits anyone, with no access control (closed test networks only).
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import tempfile
import threading
from pathlib import Path

CLOSE_TIMEOUT_S = 5.0


def _serve(router, what: str, private: Path | None = None) -> int:
    """Serve until SIGINT or SIGTERM, then close the router (``private``: a folder of secrets to remove even when
    the close hangs)."""
    print(f"zenoh router {what}", flush=True)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait()
    # Zenoh's close can wait on a link still in its handshake: a router asked to stop stops within CLOSE_TIMEOUT_S
    closing = threading.Thread(target=router.close, name="twohr-router-close", daemon=True)
    closing.start()
    closing.join(CLOSE_TIMEOUT_S)
    if closing.is_alive():
        print(f"zenoh router did not close within {CLOSE_TIMEOUT_S:.0f} s; exiting without it", flush=True)
        if private is not None:
            shutil.rmtree(private, ignore_errors=True)
        os._exit(0)
    return 0


def _fleet_router(args: argparse.Namespace) -> int:
    from twohr.bus import RouterSecurity, start_router
    from twohr.errors import TwohrError
    from twohr.identity import load_identity

    from ..access import is_loopback
    from ..fleet import USERS_FILE, write_users
    from ..fleet_router import DenialLog, FleetRouter

    keys = Path(args.keys)
    if (keys / "robots.json").is_file():  # the stack's router
        listen = args.listen or ["tls/0.0.0.0:7447"]
        if any(not endpoint.startswith("tls/") for endpoint in listen):
            raise TwohrError("a fleet's router listens on tls/ endpoints only")
        DenialLog().start()
        router = FleetRouter(keys, listen, args.ros2_domain, state=args.state)
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
        # the robot's own processes, with the robot's bundle
        users = write_users(Path(private) / USERS_FILE, {identity.name: identity.password.get_secret_value()})
        router = start_router(listen, RouterSecurity(users_file=users), connect=[upstream], identity=identity)
        return _serve(router, f"of robot {identity.name} listening on {', '.join(listen)}, linked to {upstream}",
                      Path(private))


def _router(args: argparse.Namespace) -> int:
    from twohr.bus import start_router
    from twohr.errors import TwohrError

    if args.keys:
        return _fleet_router(args)
    if not args.insecure:
        raise TwohrError("give --keys PATH (a fleet's <keys>/services/router, or a robot's bundle) or --insecure")
    listen = args.listen or ["tcp/0.0.0.0:7447"]
    return _serve(start_router(listen), f"listening on {', '.join(listen)} (INSECURE)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("router", help="run a standalone Zenoh router: a stack's (what the compose file runs) or a "
                       "robot's own", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--listen", action="append", default=None, help="endpoint(s); default tcp/0.0.0.0:7447 "
                   "(--insecure), tls/0.0.0.0:7447 (a fleet's router), tcp/127.0.0.1:7447 (a robot's router)")
    p.add_argument("--keys", default=None, metavar="PATH", help="a fleet stack's router key folder "
                   "(<keys>/services/router), or a robot's bundle for the robot's own router (see above)")
    p.add_argument("--connect", default=None, metavar="tls/HOST:PORT", help="a robot's router: the stack's router "
                   "(default: the bundle's endpoint)")
    p.add_argument("--ros2-domain", type=int, default=0, help="ROS 2 domain whose rmw_zenoh keys clients may use")
    p.add_argument("--state", default=None, metavar="FOLDER", help="a fleet stack's router: where it keeps its lease "
                   "and acknowledges each robots' list, which twohr keys revoke waits for (default <keys>/state/router "
                   "for <keys>/services/router; a container mounts that folder writable, its keys read-only)")
    p.add_argument("--insecure", action="store_true", help="admit anyone, no access control")
    p.set_defaults(func=_router)
