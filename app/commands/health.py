"""``twohr health``: ask services for their health counters over the bus, one line per replica with its host
(exit 1 if a service has no replica answering). With a robot's bundle it only checks that the stack's router admits
the robot: a robot may not read the counters, which name every replica and its host."""

from __future__ import annotations

import argparse
import json

from twohr.bus import add_router_option
from twohr.keys import PIPELINE_SERVICES


def _health(args: argparse.Namespace) -> int:
    from twohr.bus import bus_from_args, open_session, query_health
    from twohr.identity import Bundle

    conf = bus_from_args(args)
    session = open_session(conf)
    try:
        if args.bus_only:
            print("bus ok")
            return 0
        if isinstance(conf.identity, Bundle):  # a robot may not ask: the answers name every replica and its host
            print(f"bus ok: the router at {', '.join(conf.connect)} admits robot {conf.identity.name}; the services' "
                  "counters are the operator's (GET /healthz with the operator's token)")
            return 0
        names = args.names or list(PIPELINE_SERVICES)
        answers = {name: query_health(session, name, timeout=args.timeout) for name in names}
    finally:
        session.close()
    for name, health in answers.items():
        for replica in health["replicas"] if health else [None]:
            print(f"{name:10} " + ("NOT ANSWERING" if replica is None else _replica_line(replica)))
    return 0 if all(h is not None for h in answers.values()) else 1


def _replica_line(health: dict) -> str:
    counters = " ".join(f"{k}={json.dumps(v, separators=(',', ':')) if isinstance(v, (dict, list)) else v}"
                        for k, v in health.items() if k not in ("service", "replica", "host", "pid"))
    return f"{health.get('replica', '?')} on {health.get('host', '?')} pid {health.get('pid', '?')}: {counters}"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("health", help="ask services for their health counters over the bus (exit 1 if one is silent)")
    p.add_argument("names", nargs="*", help=f"services (default: {' '.join(PIPELINE_SERVICES)})")
    add_router_option(p)
    p.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for each answer")
    p.add_argument("--bus-only", action="store_true", help="only check that the router accepts a session")
    p.set_defaults(func=_health)
