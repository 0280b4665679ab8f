"""``twohr keys``: a fleet's keys. One certificate authority, one certificate per service and per robot.

    twohr keys init DIR [--host NAME]                        # the CA and every service's key folder
                                                             # ($TWOHR_API_TOKEN: the operator's API token)
    twohr keys add DIR ROBOT --out BUNDLE [--endpoint tls/HOST:PORT] [--days 365]
    twohr keys list DIR
    twohr keys revoke DIR ROBOT                              # a running stack shuts ROBOT out within seconds

A robot is given its BUNDLE alone (its certificate and key, the fleet CA, its bus password and API token, the
stack's endpoint) and joins with ``--keys BUNDLE`` (``twohr camera``, ``twohr router``, ``twohr health``, the
ros2 service). ``twohr up --keys DIR`` runs the stack on mutual TLS with these keys.
"""

from __future__ import annotations

import argparse
import datetime
import os
from pathlib import Path

from twohr.errors import TwohrError

from ..fleet import SERVICE_ROLES, Fleet


def _owners(items: list[str]) -> dict[str, int]:
    owners = {}
    for item in items:
        role, _, uid = item.rpartition("=")
        if not uid.isdigit() or (role and role not in SERVICE_ROLES):
            raise TwohrError(f"--owner {item}: give UID or ROLE=UID with ROLE one of {', '.join(SERVICE_ROLES)}")
        owners[role or "*"] = int(uid)
    return owners


def _init(args: argparse.Namespace) -> int:
    fleet = Fleet(args.dir)
    owners = _owners(args.owner or [])
    if args.if_absent and fleet.exists():
        print(f"fleet keys in {fleet.folder}: already there ({len(fleet.read().robots)} robots)")
    else:
        fleet.init(args.host or [], os.environ.get("TWOHR_API_TOKEN") or None)
        print(f"fleet keys in {fleet.folder}: CA {fleet.folder / 'ca.crt'}, one key folder per service "
              f"({', '.join(SERVICE_ROLES)}) under {fleet.folder / 'services'}; keep {fleet.folder / 'ca.key'} "
              f"private; the operator's API token is in {fleet.service_folder('gateway') / 'api-token'}")
    if owners:
        fleet.give(owners)
    return 0


def _add(args: argparse.Namespace) -> int:
    bundle = Fleet(args.dir).add(args.robot, Path(args.out), args.endpoint, args.days)
    print(f"robot {bundle.name}: bundle {args.out} (private; give it to the robot alone)"
          + (f", endpoint {bundle.endpoint}" if bundle.endpoint else ", no endpoint: the robot names one with "
             "--router"))
    return 0


def _list(args: argparse.Namespace) -> int:
    fleet = Fleet(args.dir).read()
    now = datetime.datetime.now(datetime.timezone.utc)
    print(f"{'robot':20} {'state':10} {'expires':17} serial")
    for robot, record in sorted(fleet.robots.items()):
        state = "revoked" if record.revoked else "expired" if record.not_after < now else "active"
        print(f"{robot:20} {state:10} {record.not_after:%Y-%m-%d %H:%M} {record.serial}")
    print(f"{len(fleet.robots)} robots, version {fleet.version}")
    return 0


def _revoke(args: argparse.Namespace) -> int:
    record = Fleet(args.dir).revoke(args.robot)
    print(f"robot {args.robot}: revoked at {record.revoked:%Y-%m-%d %H:%M:%S} UTC; a running stack shuts it out "
          "within a few seconds (its router restarts; the other robots reconnect by themselves)")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("keys", help="a fleet's keys: certificate authority, per-robot bundles, revocation",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    q = actions.add_parser("init", help="make the fleet's CA and one key folder per service in DIR")
    q.add_argument("dir", metavar="DIR")
    q.add_argument("--host", action="append", metavar="NAME", help="a host name or address the stack's router and "
                   "gateway are reached at, besides localhost and 127.0.0.1 (repeatable; twohr up adds its own)")
    q.add_argument("--if-absent", action="store_true", help="keep the keys already in DIR (compose's first start)")
    q.add_argument("--owner", action="append", metavar="[ROLE=]UID", help="hand the service key folders (or "
                   "ROLE's) to UID: each container reads only its own (repeatable)")
    q.set_defaults(func=_init)
    q = actions.add_parser("add", help="add a robot and write its bundle")
    q.add_argument("dir", metavar="DIR")
    q.add_argument("robot", metavar="ROBOT", help="the robot id: its certificate's common name and its keys' name")
    q.add_argument("--out", required=True, metavar="BUNDLE", help="where to write the robot's bundle (private)")
    q.add_argument("--endpoint", default=None, metavar="tls/HOST:PORT", help="the stack's router, for the robot")
    q.add_argument("--days", type=float, default=365, help="how long its certificate is valid (default 365)")
    q.set_defaults(func=_add)
    q = actions.add_parser("list", help="the fleet's robots: active, revoked or expired")
    q.add_argument("dir", metavar="DIR")
    q.set_defaults(func=_list)
    q = actions.add_parser("revoke", help="shut a robot out; a running stack applies it within seconds")
    q.add_argument("dir", metavar="DIR")
    q.add_argument("robot", metavar="ROBOT")
    q.set_defaults(func=_revoke)
