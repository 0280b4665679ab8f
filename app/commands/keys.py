"""``twohr keys``: a fleet's keys. One certificate authority, one certificate per service and per robot.

    twohr keys init DIR [--host NAME]                        # the CA and every service's key folder; the
                                                             # operator's API token in DIR/operator.token
                                                             # ($TWOHR_API_TOKEN, else a new one)
    twohr keys add-host DIR NAME...                          # the router and the gateway serve NAME too
    twohr keys add-service DIR ROLE HOST --out FOLDER        # a replica of another host, its own certificate
    twohr keys add DIR ROBOT --out BUNDLE [--endpoint tls/HOST:PORT] [--days 365]
    twohr keys renew DIR ROBOT --out BUNDLE [--days 365]     # a new certificate (a short-lived one: --days 0.5)
    twohr keys list DIR
    twohr keys revoke DIR ROBOT                              # waits (15 s) until the running stack confirms that
                                                             # ROBOT is shut out (or a replica: ROLE@HOST)
    twohr keys grant DIR ROBOT --map NAME [--remove]         # ROBOT may build or extend map NAME too

A robot is given its BUNDLE alone (its certificate and key, the fleet CA, its bus password and API token, the
stack's endpoint) and joins with ``--keys BUNDLE`` (``twohr camera``, ``twohr router``, ``twohr health``, the
ros2 service). ``twohr up --keys DIR`` runs the stack on mutual TLS with these keys, without DIR/ca.key: the CA's
private key is needed only to add a robot, a host or a replica (keep it offline otherwise); ``revoke`` runs
without it.
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
from pathlib import Path

from twohr.errors import TwohrError

from ..fleet import SERVICE_ROLES, Fleet
from ..fleet.store import MAX_ROBOT_DAYS


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
        moved = fleet.adopt_legacy_token()
        fleet.share_grants()  # the map room's copy of the grants, for keys made before it read them
        print(f"fleet keys in {fleet.folder}: already there ({len(fleet.read().robots)} robots)"
              + (f"; the operator's API token moved to {fleet.operator_token}" if moved else ""))
    else:
        fleet.init(args.host or [], os.environ.get("TWOHR_API_TOKEN") or None)
        print(f"fleet keys in {fleet.folder}: CA {fleet.folder / 'ca.crt'}, one key folder per service "
              f"({', '.join(SERVICE_ROLES)}) under {fleet.folder / 'services'}; the operator's API token is in "
              f"{fleet.operator_token}; keep {fleet.folder / 'ca.key'} offline (twohr up does not need it)")
    if owners:
        fleet.give(owners)
    return 0


def _admitted(fleet: Fleet, what: str) -> int:
    """After a robot or a replica is added: wait until a running stack's router admits it (it restarts with the new
    list), so that it can join as soon as this command returns; 1 with one line where the router could not."""
    from ..fleet_router import confirm, running

    if not running(fleet.router_state):
        print(f"{what}: no stack runs on these keys now; it is admitted when the stack starts")
        return 0
    try:
        applied = confirm(fleet.router_state, fleet.read().version)
    except TwohrError as exc:
        print(f"twohr: error: {what} is added, but {exc}", file=sys.stderr)
        return 1
    print(f"{what}: the running stack's router admits it now (list version {applied.version})")
    return 0


def _add(args: argparse.Namespace) -> int:
    fleet = Fleet(args.dir)
    bundle = fleet.add(args.robot, Path(args.out), args.endpoint, args.days, edge=args.edge)
    print(f"robot {bundle.name}{' (runs its own tracker)' if args.edge else ''}: bundle {args.out} (private; give "
          "it to the robot alone)"
          + (f", endpoint {bundle.endpoint}" if bundle.endpoint else ", no endpoint: the robot names one with "
             "--router"))
    return _admitted(fleet, f"robot {bundle.name}")


def _add_host(args: argparse.Namespace) -> int:
    names = Fleet(args.dir).add_hosts(args.names)
    print(f"the router's and the gateway's certificates name {', '.join(names)}; a running stack serves them "
          "from its next start")
    return 0


def _add_service(args: argparse.Namespace) -> int:
    fleet = Fleet(args.dir)
    name = fleet.add_service(args.role, args.host, Path(args.out), args.days)
    print(f"replica {name}: key folder {Path(args.out) / 'services' / args.role} (private; give {args.out} to "
          f"{args.host} alone, which joins with twohr up --join tls/STACK:PORT --only {args.role} --keys "
          f"{args.out}); revoke it with twohr keys revoke {args.dir} {name}")
    return _admitted(fleet, f"replica {name}")


def _list(args: argparse.Namespace) -> int:
    fleet = Fleet(args.dir).read()
    now = datetime.datetime.now(datetime.timezone.utc)
    print(f"{'robot':20} {'state':10} {'expires':17} serial")
    for robot, record in [*sorted(fleet.robots.items()), *sorted(fleet.replicas.items())]:
        state = "revoked" if record.revoked else "expired" if record.not_after < now else "active"
        edge = " (own tracker)" if getattr(record, "edge", False) else ""
        print(f"{robot:20} {state:10} {record.not_after:%Y-%m-%d %H:%M} {record.serial}{edge}")
    print(f"{len(fleet.robots)} robots, version {fleet.version}"
          + (f"; {len(fleet.replicas)} service replicas of other hosts (ROLE@HOST)" if fleet.replicas else ""))
    return 0


def _renew(args: argparse.Namespace) -> int:
    bundle = Fleet(args.dir).renew(args.robot, Path(args.out), args.days, args.endpoint)
    print(f"robot {bundle.name}: new certificate until {_not_after(bundle.cert_pem):%Y-%m-%d %H:%M:%S} UTC in "
          f"bundle {args.out} (private; give it to the robot alone); its password stays, and the bundle it had "
          "works until its own certificate expires")
    return 0


def _not_after(cert_pem: str) -> datetime.datetime:
    from cryptography import x509

    return x509.load_pem_x509_certificate(cert_pem.encode()).not_valid_after_utc


def _revoke(args: argparse.Namespace) -> int:
    from ..fleet_router import confirm

    if not 0 <= args.wait <= 600:  # False for a NaN too
        raise TwohrError(f"--wait {args.wait}: give seconds from 0 to 600")
    fleet = Fleet(args.dir)
    record = fleet.revoke(args.robot)
    version = fleet.read().version
    what = f"{'replica' if '@' in args.robot else 'robot'} {args.robot}"
    try:
        applied = confirm(fleet.router_state, version, args.wait)
    except TwohrError as exc:  # the list is saved either way: say where it stands, and fail
        print(f"twohr: error: {what} revoked in {args.dir} at {record.revoked:%Y-%m-%d %H:%M:%S} UTC, but {exc}",
              file=sys.stderr)
        return 1
    print(f"{what}: revoked at {record.revoked:%Y-%m-%d %H:%M:%S} UTC; in force: the running stack's router "
          f"applied the list of version {applied.version} and shuts it out (the other robots reconnect by "
          "themselves)")
    return 0


def _grant(args: argparse.Namespace) -> int:
    held = Fleet(args.dir).grant(args.robot, args.map, remove=args.remove)
    print(f"robot {args.robot}: {'no longer granted' if args.remove else 'granted'} map {args.map} (build and "
          f"extend); its grants: {', '.join(held) or 'none'}. A running gateway applies it at its next request")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("keys", help="a fleet's keys: certificate authority, per-robot bundles, revocation",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    q = actions.add_parser("init", help="make the fleet's CA and one key folder per service in DIR")
    q.add_argument("dir", metavar="DIR")
    q.add_argument("--host", action="append", metavar="NAME", help="a host name or address the stack's router and "
                   "gateway are reached at, besides localhost and 127.0.0.1 (repeatable; add more later with add-host)")
    q.add_argument("--if-absent", action="store_true", help="keep the keys already in DIR (compose's first start)")
    q.add_argument("--owner", action="append", metavar="[ROLE=]UID", help="hand the service key folders (or "
                   "ROLE's) to UID: each container reads only its own (repeatable)")
    q.set_defaults(func=_init)
    q = actions.add_parser("add", help="add a robot and write its bundle")
    q.add_argument("dir", metavar="DIR")
    q.add_argument("robot", metavar="ROBOT", help="the robot id: its certificate's common name and its keys' name")
    q.add_argument("--out", required=True, metavar="BUNDLE", help="where to write the robot's bundle (private; a "
                   "file there must be yours, and is replaced by a new one)")
    q.add_argument("--endpoint", default=None, metavar="tls/HOST:PORT", help="the stack's router, for the robot")
    q.add_argument("--days", type=float, default=365, help="how long its certificate is valid from now, in days "
                   f"(a fraction for hours; above 0, at most {MAX_ROBOT_DAYS}; default 365): the router closes the "
                   "robot's link when it expires")
    q.add_argument("--edge", action="store_true", help="the robot runs its own tracker (twohr camera --edge): it "
                   "may publish its own poses, paths, status and landmarks; its frames never leave it")
    q.set_defaults(func=_add)
    q = actions.add_parser("renew", help="a new certificate for a robot, in a new bundle (needs DIR/ca.key)")
    q.add_argument("dir", metavar="DIR")
    q.add_argument("robot", metavar="ROBOT")
    q.add_argument("--out", required=True, metavar="BUNDLE", help="where to write the robot's new bundle (private); "
                   "its current bundle there keeps its API token")
    q.add_argument("--days", type=float, default=365, help="how long the new certificate is valid from now, in days "
                   f"(above 0, at most {MAX_ROBOT_DAYS}; default 365)")
    q.add_argument("--endpoint", default=None, metavar="tls/HOST:PORT", help="the stack's router (default: the "
                   "current bundle's)")
    q.set_defaults(func=_renew)
    q = actions.add_parser("add-host", help="the router's and the gateway's certificates name these hosts too "
                           "(needs DIR/ca.key)")
    q.add_argument("dir", metavar="DIR")
    q.add_argument("names", nargs="+", metavar="NAME", help="a host name or address robots reach the stack at")
    q.set_defaults(func=_add_host)
    q = actions.add_parser("add-service", help="a certificate of its own for a service replica on another host "
                           "(twohr up --join); revoked as a robot is")
    q.add_argument("dir", metavar="DIR")
    q.add_argument("role", metavar="ROLE", help="the network service it runs: detector, yolo or matcher")
    q.add_argument("host", metavar="HOST", help="a label for the host it runs on (its certificate is ROLE@HOST)")
    q.add_argument("--out", required=True, metavar="FOLDER", help="where to write its key folder "
                   "(FOLDER/services/ROLE, private); several roles may share one FOLDER")
    q.add_argument("--days", type=float, default=365, help="how long its certificate is valid (default 365)")
    q.set_defaults(func=_add_service)
    q = actions.add_parser("list", help="the fleet's robots: active, revoked or expired")
    q.add_argument("dir", metavar="DIR")
    q.set_defaults(func=_list)
    q = actions.add_parser("revoke", help="shut a robot out; a running stack applies it within seconds")
    q.add_argument("dir", metavar="DIR")
    q.add_argument("robot", metavar="ROBOT")
    q.add_argument("--wait", type=float, default=15.0, metavar="S", help="how long to wait for the running stack "
                   "to confirm the new list (default 15 s); exits 1 if it does not, or if no stack runs")
    q.set_defaults(func=_revoke)
    q = actions.add_parser("grant", help="let a robot build or extend a map it did not build (every robot may "
                           "localize in any map)")
    q.add_argument("dir", metavar="DIR")
    q.add_argument("robot", metavar="ROBOT")
    q.add_argument("--map", required=True, metavar="NAME", help="the map's name in the stack's map store")
    q.add_argument("--remove", action="store_true", help="take the grant back")
    q.set_defaults(func=_grant)
