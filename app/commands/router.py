"""``twohr router``: a standalone Zenoh router with the stack's users and access control (what the compose
file's router service runs)."""

from __future__ import annotations

import argparse
import os
import signal
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


def _router(args: argparse.Namespace) -> int:
    from twohr.bus import RouterSecurity, start_router
    from twohr.errors import TwohrError

    from ..access import access_control, write_client_config

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
    print(f"zenoh router listening on {', '.join(listen)}" + (" (INSECURE)" if args.insecure else
          f", users and access control from {args.secrets}"), flush=True)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait()
    router.close()
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("router", help="run a standalone Zenoh router (what the compose file's router service runs)")
    p.add_argument("--listen", action="append", default=None, help="endpoint(s), default tcp/0.0.0.0:7447")
    p.add_argument("--secrets", default=None, metavar="DIR", help="folder of the stack's credentials, made on first "
                   "start (per-role passwords, the API token, client.json5 for outside clients)")
    p.add_argument("--client-endpoint", default=None, help="router endpoint written into client.json5 (default: "
                   "the first --listen)")
    p.add_argument("--ros2-domain", type=int, default=0, help="ROS 2 domain whose rmw_zenoh keys clients may use")
    p.add_argument("--insecure", action="store_true", help="admit anyone, no access control")
    p.set_defaults(func=_router)
