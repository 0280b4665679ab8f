"""The robots' API tokens as the gateway knows them: SHA-256 digests in the tokens file that ``twohr keys`` writes.
Checked by the HTTP API (``deps.require_token``) and the live view (``live.live_access``)."""

from __future__ import annotations

import hashlib
import json
import secrets
from pathlib import Path


class RobotTokens:
    """The robots' API tokens, as SHA-256 digests in a JSON file (``robot -> digest``, what ``twohr keys`` writes
    for the gateway); read again whenever the file changes, so a revoked robot's token stops working at once."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._stamp: tuple[int, int] | None = None
        self._robots: dict[str, str] = {}

    def robot_of(self, token: str) -> str | None:
        """The robot whose token this is, or None."""
        try:
            stat = self.path.stat()
            if (stat.st_mtime_ns, stat.st_size) != self._stamp:
                self._robots = {digest: robot for robot, digest in json.loads(self.path.read_text()).items()}
                self._stamp = (stat.st_mtime_ns, stat.st_size)
        except (OSError, ValueError):
            self._robots, self._stamp = {}, None  # unreadable: no robot is let in, the operator still is
        digest = hashlib.sha256(token.encode("utf-8", "surrogateescape")).hexdigest()
        return next((robot for known, robot in self._robots.items() if secrets.compare_digest(known, digest)), None)
