"""Opening Zenoh sessions from config, a router started from Python, and the health query.

Kept light (no numpy or OpenCV): container health checks import only this module."""

from __future__ import annotations

import json
import os
import socket
import time
from typing import Literal

import zenoh
from pydantic import BaseModel, Field

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"
#: every service answers a health query on ``twohr/_health/<name>`` with its counters
HEALTH_PREFIX = "twohr/_health"


class BusConfig(BaseModel):
    """How a process joins the bus. Multicast scouting is off by default: explicit endpoints only."""

    mode: Literal["client", "peer", "router"] = "client"
    connect: list[str] = Field(default_factory=lambda: [os.environ.get("TWOHR_ZENOH_ROUTER", DEFAULT_ROUTER)])
    listen: list[str] = Field(default_factory=list)
    multicast_scouting: bool = False

    def zenoh_config(self) -> zenoh.Config:
        conf = {
            "mode": self.mode,
            "scouting": {"multicast": {"enabled": self.multicast_scouting}},
        }
        if self.connect and self.mode != "router":
            conf["connect"] = {"endpoints": self.connect}
        if self.listen:
            conf["listen"] = {"endpoints": self.listen}
        return zenoh.Config.from_json5(json.dumps(conf))


def open_session(conf: BusConfig | None = None) -> zenoh.Session:
    """A Zenoh session as ``conf`` says (default: a client of the router at $TWOHR_ZENOH_ROUTER)."""
    return zenoh.open((conf or BusConfig()).zenoh_config())


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that is free on ``host`` right now (for routers, gateways and tests)."""
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def start_router(listen: list[str] | None = None) -> zenoh.Session:
    """A Zenoh router inside this process, listening on ``listen`` (default tcp/127.0.0.1:7447)."""
    return open_session(BusConfig(mode="router", connect=[], listen=listen or [DEFAULT_ROUTER]))


def query_health(session: zenoh.Session, service: str, timeout: float = 1.0) -> dict | None:
    """Ask one service for its health counters; None if it does not answer in time."""
    for reply in session.get(f"{HEALTH_PREFIX}/{service}", timeout=timeout):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    return None


def wait_for_services(session: zenoh.Session, names: list[str], timeout: float = 30.0) -> dict[str, dict]:
    """Block until every named service answers its health query; raises TimeoutError naming the missing ones."""
    deadline = time.monotonic() + timeout
    healthy: dict[str, dict] = {}
    while time.monotonic() < deadline:
        for name in names:
            if name not in healthy:
                answer = query_health(session, name, timeout=0.5)
                if answer is not None:
                    healthy[name] = answer
        if len(healthy) == len(names):
            return healthy
        time.sleep(0.2)
    raise TimeoutError(f"services not healthy after {timeout:.0f} s: {sorted(set(names) - set(healthy))}")
