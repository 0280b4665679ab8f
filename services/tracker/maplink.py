"""The tracker's four map calls over the bus, in one place: a stored map fetched and a session's map saved (the map
store, ``twohr/maps/<name>`` and ``twohr/maps/<name>/save``), a session's latest snapshot sent and fetched again
(``twohr/<robot>/map/snapshot``, for the tracker a session moves to when its own dies)."""

from __future__ import annotations

import logging

import zenoh

from twohr import keys
from twohr.errors import TwohrError
from twohr.mapfile import MapFile, MapFileError, encode_map, read_map
from twohr.messages import ControlMsg

#: how long the map store may take to hand over or keep a map (seconds)
MAP_TIMEOUT_S = 30.0

log = logging.getLogger("twohr.tracker")


class MapLink:
    """The map store and the session snapshots, as one tracker sees them over its bus ``session``; ``publish(key,
    payload, attachment)`` sends on it (the tracker's publishers, shared by its threads)."""

    def __init__(self, session: zenoh.Session, publish) -> None:
        self.session, self.publish = session, publish

    def fetch(self, control: ControlMsg) -> MapFile | None:
        """The map a session localizes in, extends or shares, from the map store (None: a shared map not stored
        yet); :class:`TwohrError` where the store has no such map or does not answer."""
        key = keys.map_key(control.map_name)
        for reply in self.session.get(key, timeout=MAP_TIMEOUT_S):
            if reply.ok is None and control.map_mode.stored_optional:
                return None
            if reply.ok is None:
                raise TwohrError(f"map {control.map_name}: {reply.err.payload.to_bytes().decode(errors='replace')}")
            return read_map(reply.ok.payload.to_bytes(), detector=control.config.detector)
        raise TwohrError(f"map {control.map_name}: the map store did not answer on {key} (twohr up --maps DIR)")

    def save(self, control: ControlMsg, stored: MapFile) -> None:
        """Keep ``stored`` in the map store as map ``control.map_name``'s next version; :class:`TwohrError` (why,
        in words) where the store refuses it or does not answer."""
        payload = encode_map(stored)
        key = keys.map_key(control.map_name, save=True)
        # the session's id goes with the map: the map store records its robot as an owner, and checks its rights
        for reply in self.session.get(key, payload=payload, attachment=control.session_id, timeout=MAP_TIMEOUT_S):
            if reply.ok is None:
                raise TwohrError(reply.err.payload.to_bytes().decode(errors="replace"))
            return
        raise TwohrError(f"the map store did not answer on {key}")

    def send_snapshot(self, robot_id: str, session_id: str, stored: MapFile) -> None:
        """The latest copy of a session's whole map, kept outside this process."""
        self.publish(keys.snapshot_key(robot_id), encode_map(stored), attachment=session_id)

    def fetch_snapshot(self, control: ControlMsg) -> MapFile | None:
        """The latest snapshot of a session's map (a session moved here from a tracker that died); None where none
        is kept (the session had no map yet) or it is unusable: the session starts a new map then."""
        key = keys.snapshot_key(control.robot_id)
        for reply in self.session.get(key, attachment=control.session_id, timeout=MAP_TIMEOUT_S):
            if reply.ok is None:
                log.warning("session %s: no map snapshot: %s", control.session_id,
                            reply.err.payload.to_bytes().decode(errors="replace"))
                return None
            try:
                return read_map(reply.ok.payload.to_bytes(), detector=control.config.detector)
            except MapFileError as exc:
                log.warning("session %s: its map snapshot is unusable: %s", control.session_id, exc)
                return None
        return None
