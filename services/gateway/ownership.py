"""Who may change a map: its owners (the identities that built it, in its header), the robots the operator granted
it (``twohr keys grant``, read from ``grants.json`` in the gateway's key folder whenever that file changes), and the
operator. Any robot may localize in any map; building or extending an existing one is what is guarded."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

from twohr.mapfile import OPERATOR, MapGrants

log = logging.getLogger("twohr.gateway")


def identity(robot: str | None) -> str:
    """The identity a map's owners and the audit trail name a caller by (``deps.Caller.robot``): its robot id, or
    ``@operator`` (None)."""
    return OPERATOR if robot is None else robot


class Grants:
    """The operator's map grants (``path``, as ``twohr keys grant`` writes it), read again whenever the file
    changes. No file, or an unreadable one, grants nothing (an unreadable one is logged). ``on_change`` is called
    when a change is seen, before it is used (the audit trail logs the grant before what it allowed)."""

    def __init__(self, path: Path | None, on_change: Callable[[], None] | None = None) -> None:
        self.path = path
        self.on_change = on_change
        self._stamp: tuple[int, int, int] | None = None
        self._grants = MapGrants()

    def current(self) -> MapGrants:
        """The grants in force now."""
        if self.path is None:
            return MapGrants()
        try:
            stat = self.path.stat()
            stamp = (stat.st_mtime_ns, stat.st_size, stat.st_ino)
            if stamp != self._stamp:
                self._grants, self._stamp = MapGrants.model_validate_json(self.path.read_bytes()), stamp
                if self.on_change is not None:
                    self.on_change()
        except FileNotFoundError:
            self._grants, self._stamp = MapGrants(), None
        except (OSError, ValueError) as exc:
            if self._stamp is not None or self._grants.maps:
                log.warning("map grants %s unreadable, none in force: %s", self.path, str(exc).splitlines()[0])
            self._grants, self._stamp = MapGrants(), None
        return self._grants

    def may_change(self, who: str, name: str, owners: list[str]) -> bool:
        """Whether identity ``who`` may build or extend map ``name`` owned by ``owners``."""
        return who == OPERATOR or who in owners or self.current().allows(who, name)
