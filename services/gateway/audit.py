"""The gateway's part of the audit trail (:mod:`twohr.audit`: one trail of JSON lines, private, append-only, that
the gateway, the map room and ``twohr maps`` append to; ``MAPS/audit.jsonl`` under ``twohr up`` and compose,
``audit.jsonl`` in the recordings folder unless ``--audit-log`` says otherwise). The operator reads it with
``GET /audit``; a robot's token gets 403.

The gateway logs what it does itself (sessions; maps over HTTP); the map room logs the saves it makes. What the
operator does in the keys folder the gateway notices: :class:`KeysWatch` looks at the robots' tokens
(``tokens.json``, their digests too: a token replaced between two looks is a revocation and an addition), the
router's list of replicas (``robots.json``) and the map grants (``grants.json``) four times a second, and at start
compares them with what it last saw (a private ``.audit-seen.json`` beside the log), so that a grant or a revocation
made while no stack ran is logged at the next start."""

from __future__ import annotations

import json
import logging
import threading
from pathlib import Path

from pydantic import BaseModel, Field, field_validator

from twohr.audit import STACK as STACK
from twohr.audit import AuditEvent as AuditEvent
from twohr.audit import AuditLog
from twohr.files import write_atomic
from twohr.mapfile import OPERATOR
from twohr.mapstore import MapGrants

from .tokens import WatchedFile, parse_tokens

log = logging.getLogger("twohr.gateway")

SEEN_FILE = ".audit-seen.json"
#: the router's list of the robots and replicas not revoked, in its key folder
ROUTER_LIST = "robots.json"
WATCH_PERIOD_S = 0.25


class KeysState(BaseModel):
    """What :class:`KeysWatch` last saw in the keys folder (``.audit-seen.json``); None: not known."""

    robots: dict[str, str] | None = Field(None, description="robot -> its token's SHA-256 (\"\": seen before the "
                                          "trail kept digests)")
    replicas: list[str] | None = Field(None, description="the service replicas of other hosts not revoked")
    grants: dict[str, dict[str, str]] | None = None

    @field_validator("robots", mode="before")
    @classmethod
    def _names_only(cls, robots):
        """A trail written before it kept digests listed the robots by name."""
        return {robot: "" for robot in robots} if isinstance(robots, list) else robots


def _robot_digests(data: bytes) -> dict[str, str]:
    return {robot: record.sha256 for robot, record in parse_tokens(data).items()}


def _replicas(data: bytes) -> list[str]:
    listed = json.loads(data)
    if not isinstance(listed, dict) or not isinstance(listed.get("replicas", []), list):
        raise ValueError("not a robots' list")
    return sorted(map(str, listed.get("replicas", [])))


def _grant_times(data: bytes) -> dict[str, dict[str, str]]:
    grants = MapGrants.model_validate_json(data)
    return {name: {robot: when.isoformat() for robot, when in robots.items()} for name, robots in grants.maps.items()}


class KeysWatch:
    """Logs the changes the operator makes in the keys folder: a robot added or revoked (``tokens``: robot ->
    token digest, the robots not revoked; a token replaced, as a revocation and an addition made between two looks
    leave it, is logged as both), a service replica of another host added or revoked (``replicas``: the router's
    ``robots.json``, read only; by default beside the gateway's folder, not watched where the gateway cannot see
    it, as in compose), and a map granted or withdrawn (``grants``)."""

    def __init__(self, audit: AuditLog, tokens: Path | None, grants: Path | None,
                 replicas: Path | None = None) -> None:
        self.audit = audit
        if replicas is None and tokens is not None:
            replicas = tokens.parent.parent / "router" / ROUTER_LIST
        self.tokens, self.grants, self.replicas = tokens, grants, replicas
        # None: not known (no such file given, or one not readable now); a missing tokens or grants file is empty, a
        # missing robots.json is the router's folder out of the gateway's sight
        self._files = (WatchedFile(tokens, _robot_digests, {} if tokens else None, None),
                       WatchedFile(replicas, _replicas, None, None),
                       WatchedFile(grants, _grant_times, {} if grants else None, None))
        self.seen_file = None if audit.path is None else audit.path.with_name(SEEN_FILE)
        self._last: KeysState | None = None
        self._seen: KeysState | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._polling = threading.Lock()

    def start(self) -> None:
        """Compare with what was seen before this start, then watch four times a second until :meth:`close`."""
        if self.audit.path is None or (self.tokens is None and self.grants is None):
            return
        self._thread = threading.Thread(target=self._watch, name="keys-audit", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)

    def _watch(self) -> None:
        while True:
            try:
                self.poll()
            except Exception:  # the watch goes on: the next change is logged
                log.exception("the keys folder's audit watch failed")
            if self._stop.wait(WATCH_PERIOD_S):
                return

    def poll(self) -> None:
        """Log what changed in the keys folder since it was last looked at (from the watch, and from a request that
        finds the grants changed: whichever comes first logs it)."""
        if self.audit.path is None:
            return
        with self._polling:
            self._poll()

    def _poll(self) -> None:
        robots, replicas, grants = (watched.current() for watched in self._files)
        now = KeysState(robots=robots, replicas=replicas, grants=grants)
        if now == self._last:  # the files are read again only when they change: this look cost three stats
            return
        seen = self._seen if self._seen is not None else self._load_seen()
        if seen is not None:
            self._log_changes(seen, now)
        # a file that could not be read keeps what was seen of it: its robots are not all revoked at once
        merged = KeysState(**{field: getattr(now, field) if getattr(now, field) is not None else
                              getattr(seen, field) if seen else None for field in KeysState.model_fields})
        if merged != seen:
            self._save_seen(merged)
        self._seen, self._last = merged, now

    def _log_changes(self, seen: KeysState, now: KeysState) -> None:
        if seen.robots is not None and now.robots is not None:
            for robot in sorted(set(now.robots) - set(seen.robots)):
                self.audit.record("robot.add", OPERATOR, robot=robot, detail="its token is in force")
            for robot in sorted(set(seen.robots) - set(now.robots)):
                self.audit.record("robot.revoke", OPERATOR, robot=robot, detail="its token no longer works")
            for robot in sorted(set(seen.robots) & set(now.robots)):
                if seen.robots[robot] and seen.robots[robot] != now.robots[robot]:
                    self.audit.record("robot.revoke", OPERATOR, robot=robot, detail="its token was replaced: the "
                                      "old one no longer works")
                    self.audit.record("robot.add", OPERATOR, robot=robot, detail="a new token is in force (added "
                                      "again, or renewed with a new token)")
        if seen.replicas is not None and now.replicas is not None:
            for name in sorted(set(now.replicas) - set(seen.replicas)):
                self.audit.record("robot.add", OPERATOR, robot=name, detail="service replica: its certificate is "
                                  "in force")
            for name in sorted(set(seen.replicas) - set(now.replicas)):
                self.audit.record("robot.revoke", OPERATOR, robot=name, detail="service replica: its certificate "
                                  "and password no longer work")
        if seen.grants is not None and now.grants is not None:
            for name, robot, when in _pairs(now.grants, seen.grants):
                self.audit.record("map.grant", OPERATOR, robot=robot, map=name, detail=f"granted at {when}")
            for name, robot, _ in _pairs(seen.grants, now.grants):
                self.audit.record("map.ungrant", OPERATOR, robot=robot, map=name, detail="grant withdrawn")

    def _load_seen(self) -> KeysState | None:
        try:
            return KeysState.model_validate_json(self.seen_file.read_bytes())
        except FileNotFoundError:
            return None  # the first start: what is there now is where the trail begins
        except (OSError, ValueError):
            log.warning("%s unreadable: changes in the keys folder before this start are not in the audit trail",
                        self.seen_file)
            return None

    def _save_seen(self, state: KeysState) -> None:
        write_atomic(self.seen_file, state.model_dump_json())


def _pairs(ours: dict[str, dict[str, str]], theirs: dict[str, dict[str, str]]) -> list[tuple[str, str, str]]:
    """(map, robot, when) of each grant in ``ours`` that ``theirs`` lacks."""
    return [(name, robot, when) for name, robots in sorted(ours.items()) for robot, when in sorted(robots.items())
            if robot not in theirs.get(name, {})]

