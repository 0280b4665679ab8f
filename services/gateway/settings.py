"""The gateway's configuration (``GatewaySettings``): each field is a flag of ``python -m twohr_services.gateway``,
made from the field (its name, type and description) by ``__main__.add_settings_flags``."""

from __future__ import annotations

import os
from pathlib import Path

from pydantic import BaseModel, Field, field_validator

from twohr.bus import BusConfig
from twohr.identity import api_token_problem
from twohr.mapstore import GRANTS_FILE


class GatewaySettings(BaseModel):
    """Gateway configuration: one flag of ``python -m twohr_services.gateway`` per field (``--<field-name>``, its
    help the description; ``bus`` is ``--router``/``--keys``)."""

    data_roots: list[Path] = Field(default_factory=lambda: [Path("data")], description="folders sequences may "
                                   "come from (POST /sessions names a sequence relative to one, or inside one)")
    recordings: Path = Field(Path("recordings"), description="folder the recorder writes MCAP files to")
    api_token: str | None = Field(default_factory=lambda: os.environ.get("TWOHR_API_TOKEN") or None,
                                  validate_default=True, description="if set, requests need 'Authorization: Bearer "
                                  "<token>' (at least 16 characters: a blank token is refused)")
    robot_tokens: Path | None = Field(None, description="the robots' API tokens (robot -> SHA-256 and expiry, JSON, as "
                                      "twohr keys writes it): a robot's token starts, stops and reads its own sessions "
                                      "only, until its certificate expires")
    bus: BusConfig = Field(default_factory=BusConfig, description="how the gateway joins the bus")
    idle_timeout: float = Field(15.0, gt=0, description="a session whose source is done and that gets no pose "
                                "for this long is finished")
    start_timeout: float = Field(180.0, gt=0, description="a session with no pose this long after its start fails")
    stall_timeout: float = Field(45.0, gt=0, description="a running session with no pose for this long fails")
    refine_timeout: float = Field(30.0, gt=0, description="after a session ends, how long its refined trajectory "
                                  "(from the tracker) is waited for before the online poses are served instead")
    liveliness_grace: float = Field(0.5, ge=0, description="a pipeline service whose liveliness token stays away this "
                                    "long, while the gateway stays linked to its router, fails the active sessions")
    keep_ended: int = Field(200, ge=1, description="ended sessions kept in the table (the oldest are forgotten)")
    max_robots: float | None = Field(None, gt=0, description="robots the stack carries at 30 Hz (a session at "
                                     "\"rate\" 15 counts half); past it POST /sessions gets 503 with Retry-After. "
                                     "None = no limit (twohr up sets it: --max-robots, default auto: measured)")
    max_request_bytes: int = Field(256 * 1024, ge=1024, description="larger request bodies get 413")
    foxglove_host: str = Field("127.0.0.1", description="interface of the Foxglove live view")
    foxglove_port: int | None = Field(None, ge=0, le=65535, description="Foxglove live view port; None = off")
    tls_keys: Path | None = Field(None, description="the gateway's key folder (cert.pem, key.pem of a fleet's keys): "
                                  "HTTPS, and the live view on TLS with a token (?token=, the operator's or a "
                                  "robot's); None = neither")
    maps: Path | None = Field(None, description="the map store's folder (served on /maps; on the bus by the map "
                              "room, given the same folder); None = no map store")
    max_map_bytes: int = Field(512 * 1024 * 1024, ge=1024, description="larger map uploads get 413")
    map_versions: int = Field(10, ge=1, le=10_000, description="versions of each map the store keeps (past it the "
                              "oldest go; the others keep their numbers)")
    map_grants: Path | None = Field(None, description="the operator's map grants (grants.json, as twohr keys grant "
                                    "writes it); None = grants.json beside robot_tokens")
    audit_log: Path | None = Field(None, description="the audit trail (JSON lines, private, append-only; GET "
                                   "/audit); None = audit.jsonl in the recordings folder")

    @field_validator("api_token")
    @classmethod
    def _usable_token(cls, token: str | None) -> str | None:
        """A token that is set must be one: a blank one would equal a request's missing header."""
        problem = None if token is None else api_token_problem(token)
        if problem is not None:
            raise ValueError(problem)
        return token

    def grants_file(self) -> Path | None:
        """Where the operator's map grants are read from (None: no robots' tokens, so no grants either)."""
        return self.map_grants or (self.robot_tokens.parent / GRANTS_FILE if self.robot_tokens else None)

    def audit_file(self) -> Path:
        """Where the audit trail is written."""
        return self.audit_log or self.recordings / "audit.jsonl"
