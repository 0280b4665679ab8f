"""The map room over the bus: one client for what the map room serves, and the words both ends agree on.

The map room (``twohr_services.mapserver``) holds the map store and each live session's latest map snapshot. Over
the bus it answers:

- ``twohr/maps/<name>`` (:func:`twohr.keys.map_key`): the latest version's bytes of a stored map; a map the store
  lacks is an error reply that begins with :data:`NO_MAP`;
- ``twohr/maps/<name>/save``, a map file's bytes as payload and the id of the session that built it as attachment
  (none: the operator's, the stack's): the map kept as its next version, the reply its
  :class:`~twohr.mapstore.MapEntry` as JSON, or an error reply that says why not (not a map, not the session's map,
  not the session's starter's to change);
- ``twohr/<robot>/map/snapshot`` (:func:`twohr.keys.snapshot_key`): the tracker publishes its latest copy of a live
  session's map there every few seconds, the session's id attached; a query with that id attached is answered with
  it, while the session is active (:data:`NO_SNAPSHOT` otherwise), for the tracker the session moves to.

:class:`MapClient` is the other end, for any process with a Zenoh session that the bus's access control lets ask
(the tracker fetches, saves and moves; a client fetches).
"""

from __future__ import annotations

from collections.abc import Callable

import zenoh

from . import keys
from .config import DetectorConfig
from .errors import TwohrError
from .mapfile import MapFile, MapFileError, encode_map, read_map
from .mapstore import MapEntry, MapMissingError

#: how long an answer of the map room is waited for by default (a large map's bytes cross the bus in it)
TIMEOUT_S = 30.0
#: what the map room's error reply to a read of a map the store lacks begins with
NO_MAP = "no map named"
#: the map room's error reply to a snapshot query it holds none for
NO_SNAPSHOT = "no snapshot of this session's map"


def no_map(name: str) -> str:
    """The map room's error reply to a read of map ``name`` where the store holds none."""
    return f"{NO_MAP} {name!r} in the map store"


class MapRoomUnreachable(TwohrError):
    """The map room did not answer: it is not running, or keeps no map store (``twohr up --maps DIR``)."""


#: how a snapshot is sent: ``publish(key, payload, attachment)``
Publish = Callable[[str, bytes, str], None]


class MapClient:
    """Maps and snapshots from and to the map room, over ``session`` (answers waited for ``timeout`` s).
    ``publish`` sends a snapshot (a service's own publishers, say); by default a put on ``session``."""

    def __init__(self, session: zenoh.Session, timeout: float = TIMEOUT_S, publish: Publish | None = None) -> None:
        self.session = session
        self.timeout = timeout
        self.publish = publish or self._put

    def fetch(self, name: str, detector: DetectorConfig | None = None, optional: bool = False) -> MapFile | None:
        """The latest version of stored map ``name``, checked through (with ``detector``: built with it too).
        A map the store lacks: None if ``optional``, else :class:`~twohr.mapstore.MapMissingError`; a map that
        cannot be read or used: :class:`~twohr.mapfile.MapFileError`; no answer: :class:`MapRoomUnreachable`."""
        data = self._ask(keys.map_key(name), f"map {name}")
        if isinstance(data, str):
            if not data.startswith(NO_MAP):
                raise MapFileError(f"map {name}: {data}")
            if optional:
                return None
            raise MapMissingError(f"map {name}: {data}")
        return read_map(data, detector=detector)

    def save(self, map_file: MapFile, session_id: str | None = None) -> MapEntry:
        """Keep ``map_file`` in the store as the next version of its map, built by session ``session_id`` (None:
        the operator's); its entry. Refused: :class:`~twohr.mapfile.MapFileError` saying why; no answer:
        :class:`MapRoomUnreachable`."""
        name = map_file.header.name
        answer = self._ask(keys.map_key(name, save=True), f"map {name}", payload=encode_map(map_file),
                           attachment=session_id)
        if isinstance(answer, str):
            raise MapFileError(answer)
        return MapEntry.model_validate_json(answer)

    def send_snapshot(self, robot_id: str, session_id: str, map_file: MapFile) -> int:
        """Publish the latest copy of session ``session_id``'s map (robot ``robot_id``'s) for the map room to keep;
        the bytes sent."""
        data = encode_map(map_file)
        self.publish(keys.snapshot_key(robot_id), data, session_id)
        return len(data)

    def fetch_snapshot(self, robot_id: str, session_id: str, detector: DetectorConfig | None = None) -> MapFile:
        """The latest snapshot the map room keeps of session ``session_id``'s map (robot ``robot_id``'s), checked
        through. None kept, or one that cannot be used: :class:`~twohr.mapfile.MapFileError` saying why; no answer:
        :class:`MapRoomUnreachable`."""
        answer = self._ask(keys.snapshot_key(robot_id), f"session {session_id}'s map snapshot",
                           attachment=session_id)
        if isinstance(answer, str):
            raise MapFileError(answer)
        return read_map(answer, detector=detector)

    def _put(self, key: str, payload: bytes, attachment: str) -> None:
        self.session.put(key, payload, attachment=attachment, congestion_control=zenoh.CongestionControl.BLOCK)

    def _ask(self, key: str, what: str, payload: bytes | None = None, attachment: str | None = None) -> bytes | str:
        """The first answer to a query on ``key``: its bytes, or the text of an error reply;
        :class:`MapRoomUnreachable` when none comes in time."""
        for reply in self.session.get(key, payload=payload, attachment=attachment, timeout=self.timeout):
            if reply.ok is not None:
                return reply.ok.payload.to_bytes()
            return reply.err.payload.to_bytes().decode(errors="replace")
        raise MapRoomUnreachable(f"{what}: the map room did not answer on {key} (twohr up --maps DIR)")
