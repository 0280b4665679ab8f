"""Who a token is, as the gateway knows it: the operator's API token, and the robots' tokens as SHA-256 digests in the
tokens file that ``twohr keys`` writes (each with its certificate's expiry). One check, :meth:`Tokens.identify`,
serves the HTTP API (``deps.require_token``) and the live view (``live.live_access``), so the two cannot drift.

The live view also takes a **view token** (:func:`view_token`): HMAC-SHA256 keyed with the SHA-256 of an API token,
which the gateway can compute from what it knows (the operator's token, a robot's digest) and which opens the live
view only: the HTTP API refuses it. It is what goes into a Foxglove URL, so that the API token never leaves for a
third-party page. :class:`WatchedFile` is the one way the gateway reads a file the keys folder may change under it
(the tokens, the grants, the audit's watch)."""

from __future__ import annotations

import datetime
import hashlib
import hmac
import json
import logging
import secrets
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Generic, TypeVar

from fastapi import HTTPException, status
from pydantic import BaseModel

log = logging.getLogger("twohr.gateway")

T = TypeVar("T")
VIEW_PREFIX = "view-"
VIEW_CONTEXT = b"twohr live view"


def file_stamp(path: Path) -> tuple[int, int, int]:
    """What says a file changed: its inode (a replaced file, as the keys folder's writes replace it), its
    modification time and its size. OSError when it cannot be looked at."""
    stat = path.stat()
    return stat.st_ino, stat.st_mtime_ns, stat.st_size


class WatchedFile(Generic[T]):
    """``path``'s content as ``parse`` makes it of the bytes, read again only when :func:`file_stamp` changes. No
    path, or no file, is ``missing``; a file that cannot be read or parsed is ``broken`` (logged once per change).
    ``on_change`` is called when a change is seen, before the new content is used."""

    def __init__(self, path: Path | None, parse: Callable[[bytes], T], missing: T, broken: T,
                 on_change: Callable[[], None] | None = None) -> None:
        self.path, self.parse, self.missing, self.broken, self.on_change = path, parse, missing, broken, on_change
        self._stamp: tuple[int, int, int] | None = None
        self._value: T = missing

    def current(self) -> T:
        """The content now."""
        if self.path is None:
            return self.missing
        try:
            stamp = file_stamp(self.path)
        except FileNotFoundError:
            stamp = None
        except OSError as exc:
            return self._set(("unreadable",), self.broken, exc)
        if stamp is None:
            return self._set(None, self.missing)
        if stamp == self._stamp:
            return self._value
        try:
            value = self.parse(self.path.read_bytes())
        except FileNotFoundError:  # replaced between the stat and the read: the next look finds the new one
            return self._value
        except (OSError, ValueError) as exc:
            return self._set(stamp, self.broken, exc)
        return self._set(stamp, value)

    def _set(self, stamp, value: T, problem: Exception | None = None) -> T:
        if stamp != self._stamp:
            if problem is not None:
                log.warning("%s unreadable: %s", self.path, str(problem).splitlines()[0] if str(problem) else
                            type(problem).__name__)
            self._stamp, self._value = stamp, value
            if self.on_change is not None:
                self.on_change()
        return self._value


@dataclass(frozen=True)
class Caller:
    """Who sent a request: the operator (``robot`` None: everything) or one robot (its own sessions only)."""

    robot: str | None = None

    def check_robot(self, robot_id: str) -> None:
        """403 unless this caller may act for ``robot_id``."""
        if self.robot is not None and self.robot != robot_id:
            raise HTTPException(status.HTTP_403_FORBIDDEN, f"robot {self.robot}'s token acts for robot "
                                f"{self.robot} only, not {robot_id}")

    def check_operator(self, what: str) -> None:
        """403 unless this caller is the operator."""
        if self.robot is not None:
            raise HTTPException(status.HTTP_403_FORBIDDEN, f"{what} needs the operator's token, not robot "
                                f"{self.robot}'s")


class TokenRecord(BaseModel):
    """A robot's entry in the tokens file: its API token's SHA-256 (hex) and when its certificate expires (its token
    stops working then too; None in a file written before expiry was recorded)."""

    sha256: str
    not_after: datetime.datetime | None = None

    def expired(self, now: datetime.datetime) -> bool:
        if self.not_after is None:
            return False
        until = self.not_after if self.not_after.tzinfo else self.not_after.replace(tzinfo=datetime.timezone.utc)
        return now >= until


def _key_view(key: bytes) -> str:
    return VIEW_PREFIX + hmac.new(key, VIEW_CONTEXT, hashlib.sha256).hexdigest()


def view_token(api_token: str) -> str:
    """The live view's token of an API token: opens the live view with the same sight, and nothing of the HTTP API."""
    return _key_view(hashlib.sha256(api_token.encode("utf-8", "surrogateescape")).digest())


@dataclass(frozen=True)
class _Robots:
    """The tokens file, parsed: robot -> record, and each robot's view token."""

    records: dict[str, TokenRecord] = field(default_factory=dict)
    views: dict[str, str] = field(default_factory=dict)


def parse_tokens(data: bytes) -> dict[str, TokenRecord]:
    """The tokens file: ``{robot: {"sha256": ..., "not_after": ISO time}}``, or the earlier ``{robot: digest}``."""
    raw = json.loads(data)
    if not isinstance(raw, dict):
        raise ValueError("not a JSON object of robots")
    return {str(robot): TokenRecord(sha256=value) if isinstance(value, str) else TokenRecord.model_validate(value)
            for robot, value in raw.items()}


def _parse_robots(data: bytes) -> _Robots:
    records = parse_tokens(data)
    views = {}
    for robot, record in records.items():
        try:
            views[robot] = _key_view(bytes.fromhex(record.sha256))
        except ValueError:
            log.warning("robot %s's token digest in the tokens file is not hex: its view token is refused", robot)
    return _Robots(records, views)


class RobotTokens:
    """The robots' API tokens (a JSON file, what ``twohr keys`` writes for the gateway), read again whenever the file
    changes, so a revoked robot's token stops working at once; a robot past its ``not_after`` is refused too. An
    unreadable file lets no robot in (the operator still is)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._file = WatchedFile(path, _parse_robots, _Robots(), _Robots())

    def robot_of(self, token: str) -> str | None:
        """The robot whose API token this is, or None (none, or past its expiry)."""
        digest = hashlib.sha256(token.encode("utf-8", "surrogateescape")).hexdigest()
        robots = self._file.current()
        found = [robot for robot, record in robots.records.items()
                 if secrets.compare_digest(record.sha256.encode("utf-8", "surrogateescape"), digest.encode())]
        return self._in_force(robots, found)

    def robot_of_view(self, token: str) -> str | None:
        """The robot whose view token this is, or None (none, or past its expiry)."""
        robots = self._file.current()
        found = [robot for robot, view in robots.views.items()
                 if secrets.compare_digest(view.encode(), token.encode("utf-8", "surrogateescape"))]
        return self._in_force(robots, found)

    @staticmethod
    def _in_force(robots: _Robots, found: list[str]) -> str | None:
        if not found:
            return None
        robot = found[0]
        if robots.records[robot].expired(datetime.datetime.now(datetime.timezone.utc)):
            log.info("refused robot %s's token: its certificate expired at %s", robot, robots.records[robot].not_after)
            return None
        return robot


class Tokens:
    """The gateway's token check: the operator's API token (``operator``; None: none) and the robots' (``robots``,
    the tokens file; None: none). With neither, every caller is the operator (a gateway on loopback with no token)."""

    def __init__(self, operator: str | None, robots: Path | None) -> None:
        self.operator = operator or None
        self.robots = RobotTokens(robots) if robots is not None else None
        self._operator_view = view_token(self.operator) if self.operator else None

    @property
    def required(self) -> bool:
        """Whether a request needs a token at all."""
        return self.operator is not None or self.robots is not None

    def identify(self, token: str) -> Caller | None:
        """Who this API token is (the HTTP API's check), or None: no token, a wrong one, or an expired robot's."""
        if not token:
            return None
        # compared as bytes: a token with non-ASCII characters is simply a wrong one
        if self.operator and secrets.compare_digest(token.encode("utf-8", "surrogateescape"), self.operator.encode()):
            return Caller()
        robot = self.robots.robot_of(token) if self.robots is not None else None
        return Caller(robot) if robot is not None else None

    def identify_viewer(self, token: str) -> Caller | None:
        """Who may watch with this token (the live view's check): an API token, as :meth:`identify`, or a view
        token (:func:`view_token`) of one."""
        caller = self.identify(token)
        if caller is not None or not token.startswith(VIEW_PREFIX):
            return caller
        if self._operator_view and secrets.compare_digest(token.encode("utf-8", "surrogateescape"),
                                                          self._operator_view.encode()):
            return Caller()
        robot = self.robots.robot_of_view(token) if self.robots is not None else None
        return Caller(robot) if robot is not None else None
