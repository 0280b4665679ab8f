"""The tracker's four map calls, as a session's control message asks them of the map room over the bus
(:class:`twohr.mapclient.MapClient`): a stored map fetched and a session's map saved (``twohr/maps/<name>`` and
``twohr/maps/<name>/save``), a session's latest snapshot sent and fetched again (``twohr/<robot>/map/snapshot``, for
the tracker a session moves to when its own dies)."""

from __future__ import annotations

import logging

import zenoh

from twohr.mapclient import MapClient, MapRoomUnreachable, Publish
from twohr.mapfile import MapFile, MapFileError
from twohr.messages import ControlMsg

log = logging.getLogger("twohr.tracker")


class MapLink:
    """The map room as one tracker's sessions see it over its bus ``session``; ``publish(key, payload, attachment)``
    sends a snapshot (the tracker's publishers, shared by its threads)."""

    def __init__(self, session: zenoh.Session, publish: Publish) -> None:
        self.client = MapClient(session, publish=publish)

    def fetch(self, control: ControlMsg) -> MapFile | None:
        """The map a session localizes in, extends or shares, from the map store (None: a shared map not stored
        yet); :class:`~twohr.errors.TwohrError` where the store has no such map, it cannot be used, or the map room
        does not answer."""
        return self.client.fetch(control.map_name, control.config.detector,
                                 optional=control.map_mode.stored_optional)

    def save(self, control: ControlMsg, stored: MapFile) -> None:
        """Keep ``stored`` in the map store as map ``control.map_name``'s next version; the session's id goes with it
        (the map room records its robot as an owner, and checks its rights). :class:`~twohr.errors.TwohrError`
        (why, in words) where the map room refuses it or does not answer."""
        self.client.save(stored, control.session_id)

    def send_snapshot(self, robot_id: str, session_id: str, stored: MapFile) -> None:
        """The latest copy of a session's whole map, for the map room to keep outside this process."""
        self.client.send_snapshot(robot_id, session_id, stored)

    def fetch_snapshot(self, control: ControlMsg) -> MapFile | None:
        """The latest snapshot the map room keeps of a session's map (a session moved here from a tracker that
        died); None where none is kept (the session had no map yet), it is unusable or the map room does not answer:
        the session starts a new map then."""
        try:
            return self.client.fetch_snapshot(control.robot_id, control.session_id, control.config.detector)
        except (MapFileError, MapRoomUnreachable) as exc:
            log.warning("session %s: no usable map snapshot: %s", control.session_id, exc)
            return None
