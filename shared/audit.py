"""The audit trail: who started, stopped or failed a session, who saved, uploaded, rolled back or deleted a map, who
was granted a map and who was added or revoked, with the time, as JSON lines appended to one private file (0600).

One trail per stack, written by several processes: the gateway (sessions, maps over HTTP, the keys folder's
changes), the map room (the saves of maps, under the map store's lock) and ``twohr maps rollback``; ``twohr up`` and
compose give them all the same file (``MAPS/audit.jsonl``). Lines are only ever appended (``O_APPEND``, one
``write`` each, fsynced), so writers in several processes never cut into each other's lines; nothing here rewrites
or truncates the log. The operator reads it with the gateway's ``GET /audit``."""

from __future__ import annotations

import datetime
import logging
import os
import threading
import time
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, Field, ValidationError

from .mapfile import OPERATOR

log = logging.getLogger("twohr.audit")

#: the identity of what the stack does by itself: a session that finished or failed, a map saved with no session
STACK = "@stack"
#: the audit events, by what happened
Action = Literal["session.start", "session.stop", "session.finish", "session.fail", "session.move", "map.save",
                 "map.upload", "map.rollback", "map.delete", "map.grant", "map.ungrant", "map.remove_robot",
                 "robot.add", "robot.revoke"]


class AuditEvent(BaseModel):
    """One line of the audit trail."""

    time: float = Field(description="when it was logged (Unix time)")
    utc: str = Field(description="the same time, ISO 8601 in UTC")
    action: Action
    who: str = Field(description=f"who did it: a robot id, {OPERATOR} (the operator's token, the keys folder, "
                     f"twohr maps) or {STACK} (the stack: a session that finished or failed)")
    robot: str | None = Field(None, description="the robot acted on or for")
    session: str | None = None
    map: str | None = None
    version: int | None = Field(None, description="the map version made (saved, uploaded, rolled back to)")
    detail: str = ""


class AuditLog:
    """The append-only audit trail in ``path`` (None: events are made and dropped, for a process with no log)."""

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self._lock = threading.Lock()

    def record(self, action: Action, who: str, **fields) -> AuditEvent:
        """Append one event; a log that cannot be written is an error in this process's log, not in what it
        records."""
        now = time.time()
        event = AuditEvent(time=now, utc=datetime.datetime.fromtimestamp(now, datetime.timezone.utc).isoformat(
            timespec="milliseconds"), action=action, who=who, **fields)
        if self.path is None:
            return event
        line = (event.model_dump_json(exclude_none=True) + "\n").encode()
        try:
            with self._lock:
                append_private(self.path, line)
        except OSError as exc:
            log.error("audit trail %s not written (%s): %s", self.path, exc.strerror or exc, line.decode().strip())
        return event

    def read(self, limit: int = 1000, since: float | None = None) -> list[AuditEvent]:
        """The newest ``limit`` events (from ``since``, Unix time, if given), oldest first. A line that is not an
        event (cut short by a power loss) is left out and logged."""
        if self.path is None or not self.path.is_file():
            return []
        events = []
        for number, line in enumerate(self.path.read_bytes().splitlines(), 1):
            try:
                event = AuditEvent.model_validate_json(line)
            except ValidationError:
                log.warning("audit trail %s line %d is not an event", self.path, number)
                continue
            if since is None or event.time >= since:
                events.append(event)
        return events[-limit:]


def append_private(path: Path, data: bytes) -> None:
    """Append ``data`` to ``path`` in one write, creating it readable by its owner only (0600); a file found wider
    is narrowed first."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
    try:
        if os.fstat(handle).st_mode & 0o077:
            os.fchmod(handle, 0o600)
        os.write(handle, data)
        os.fsync(handle)
    finally:
        os.close(handle)
