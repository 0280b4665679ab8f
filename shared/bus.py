"""Opening Zenoh sessions from config, and a router started from Python."""

from __future__ import annotations

import json
import os
import socket
from typing import Literal

import zenoh
from pydantic import BaseModel, Field

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"


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
