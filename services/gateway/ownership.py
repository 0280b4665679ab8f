"""Who may change a map: its owners (the identities that built it, in its header), the robots the operator granted
it (``twohr keys grant``, read from ``grants.json`` in the gateway's key folder whenever that file changes), and the
operator. Any robot may localize in any map; building or extending an existing one is what is guarded."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from twohr.mapfile import OPERATOR
from twohr.mapstore import MapGrants, may_change

from .tokens import WatchedFile


def identity(robot: str | None) -> str:
    """The identity a map's owners and the audit trail name a caller by (``deps.Caller.robot``): its robot id, or
    ``@operator`` (None)."""
    return OPERATOR if robot is None else robot


class Grants:
    """The operator's map grants (``path``, as ``twohr keys grant`` writes it), read again whenever the file
    changes (:class:`~.tokens.WatchedFile`). No file, or an unreadable one, grants nothing (an unreadable one is
    logged). ``on_change`` is called when a change is seen, before it is used (the audit trail logs the grant before
    what it allowed)."""

    def __init__(self, path: Path | None, on_change: Callable[[], None] | None = None) -> None:
        self.path = path
        self._file = WatchedFile(path, MapGrants.model_validate_json, MapGrants(), MapGrants(), on_change)

    def current(self) -> MapGrants:
        """The grants in force now."""
        return self._file.current()

    def may_change(self, who: str, name: str, owners: list[str]) -> bool:
        """Whether identity ``who`` may build or extend map ``name`` owned by ``owners``, with the grants in force
        (:func:`twohr.mapstore.may_change`, the rule the map room checks a save with)."""
        return may_change(who, name, owners, self.current())
