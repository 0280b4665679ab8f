"""The map room's store side, with no bus: the map store (:mod:`twohr.mapstore`), each session's start as the map
room heard it, the live sessions' latest map snapshots, and who may save what.

A save names the session that built the map (the tracker attaches its id; the map room saves a shared map on behalf
of the session that opened it). The session's control message says who started it (``started_by``: the robot whose
token did, or the operator) and what it does with which map: a save is refused unless that session saves (build,
extend, share) that map, and replacing an existing map needs its starter to own it or hold the operator's grant
(:func:`twohr.mapstore.may_change`, the grants read at each save). The session's robot is the builder: a new map's
owner, a contributor to another's. Each save is appended to the audit trail under the store's lock; a refusal on
rights is too. A save that names no session is the operator's (only the stack's processes may ask one)."""

from __future__ import annotations

import logging
import threading
from collections import Counter, OrderedDict
from dataclasses import dataclass
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field

from twohr.audit import STACK, AuditLog
from twohr.config import DetectorConfig
from twohr.errors import TwohrError
from twohr.mapclient import no_map
from twohr.mapfile import OPERATOR, MapFile, MapFileError, read_map
from twohr.mapstore import (
    DEFAULT_KEEP,
    MAX_KEEP,
    MapAccessError,
    MapEntry,
    MapGrants,
    MapMissingError,
    MapStore,
    may_change,
)
from twohr.messages import ControlMsg

log = logging.getLogger("twohr.mapserver")

#: ended sessions whose start is kept (their tracker saves their map after the end; the oldest are forgotten)
KEEP_ENDED = 200
#: the audit trail's file in the map store's folder, unless told otherwise
AUDIT_FILE = "audit.jsonl"


class MapRoomSettings(BaseModel):
    """The map room's store (flags of ``python -m twohr_services.mapserver``)."""

    model_config = ConfigDict(extra="forbid")

    maps: Path | None = Field(None, description="the map store's folder, served on twohr/maps/<name>; None = no map "
                              "store (shared maps live while their sessions run, and are not saved)")
    map_versions: int = Field(DEFAULT_KEEP, ge=1, le=MAX_KEEP, description="versions of each map the store keeps "
                              "(past it the oldest go; the others keep their numbers)")
    map_grants: Path | None = Field(None, description="the operator's map grants (grants.json, as twohr keys grant "
                                    "writes it); None = none: a map is changed by its owners and the operator")
    audit_log: Path | None = Field(None, description=f"the audit trail the saves are appended to (the gateway's, "
                                   f"GET /audit); None = {AUDIT_FILE} in the map store's folder")

    def audit_file(self) -> Path | None:
        """Where the saves are audited (None: nowhere, a room with no store)."""
        return self.audit_log or (self.maps / AUDIT_FILE if self.maps is not None else None)


@dataclass
class SessionRecord:
    """A session as the map room knows it: its start, whether it ended, its map's latest snapshot while active."""

    control: ControlMsg
    ended: bool = False
    snapshot: bytes | None = None


class SessionBook:
    """Each session's start, by id (the ended ones too, the latest :data:`KEEP_ENDED` of them: a tracker saves a
    session's map after its end), and the active sessions' snapshots. Thread-safe: the controls come on the service's
    thread, the snapshots and the queries on Zenoh's and the store's."""

    def __init__(self, keep_ended: int = KEEP_ENDED) -> None:
        self.keep_ended = keep_ended
        self._sessions: OrderedDict[str, SessionRecord] = OrderedDict()
        self._lock = threading.Lock()

    def started(self, control: ControlMsg) -> None:
        """A session starts (or starts again: what was kept of it goes). A robot runs one session at a time: its
        earlier one ended, though its stop never came here (the room was away), and its snapshot goes."""
        with self._lock:
            self._sessions.pop(control.session_id, None)
            for record in self._sessions.values():
                if record.control.robot_id == control.robot_id:
                    record.ended, record.snapshot = True, None
            self._sessions[control.session_id] = SessionRecord(control)

    def stopped(self, session_id: str) -> None:
        """A session ended: its snapshot goes, its start is kept for the save that may follow."""
        with self._lock:
            record = self._sessions.get(session_id)
            if record is None:
                return
            record.ended, record.snapshot = True, None
            ended = [sid for sid, r in self._sessions.items() if r.ended]
            for old in ended[:max(0, len(ended) - self.keep_ended)]:
                del self._sessions[old]

    def control(self, session_id: str) -> ControlMsg | None:
        """The start of session ``session_id`` (active or ended), None for a session the room did not hear of."""
        with self._lock:
            record = self._sessions.get(session_id)
            return None if record is None else record.control

    def active(self, session_id: str) -> bool:
        """Whether session ``session_id`` started and has not ended, as the room heard it."""
        with self._lock:
            record = self._sessions.get(session_id)
            return record is not None and not record.ended

    def keep_snapshot(self, robot: str, session_id: str, data: bytes) -> bool:
        """Keep ``data`` as the latest snapshot of session ``session_id``'s map, where that is an active session of
        robot ``robot`` (the one the snapshot's key names); False (and nothing kept) otherwise."""
        with self._lock:
            record = self._active(robot, session_id)
            if record is not None:
                record.snapshot = data
            return record is not None

    def snapshot(self, robot: str, session_id: str) -> bytes | None:
        """The latest snapshot of an active session of robot ``robot``; None where none is kept."""
        with self._lock:
            record = self._active(robot, session_id)
            return None if record is None else record.snapshot

    def snapshots(self) -> int:
        """How many snapshots are kept now."""
        with self._lock:
            return sum(record.snapshot is not None for record in self._sessions.values())

    def _active(self, robot: str, session_id: str) -> SessionRecord | None:
        record = self._sessions.get(session_id)
        if record is None or record.ended or record.control.robot_id != robot:
            return None
        return record


def saved_names(control: ControlMsg) -> tuple[str, ...]:
    """The maps a session may save: its map, where its mode saves one; for a shared map also ``<name>.<robot>``,
    where the map room keeps a robot that never merged."""
    if not control.map_mode.saves:
        return ()
    if control.map_mode.shared:
        return control.map_name, f"{control.map_name}.{control.robot_id}"
    return (control.map_name,)


class MapRoom:
    """The store, the sessions and the audit of saves (see the module). ``reads`` counts the reads of each stored
    map (served over the bus, or opened for a shared map)."""

    def __init__(self, settings: MapRoomSettings, audit: AuditLog | None = None) -> None:
        self.settings = settings
        self.store = None if settings.maps is None else MapStore(settings.maps, settings.map_versions)
        self.sessions = SessionBook()
        self.audit = audit or AuditLog(settings.audit_file())
        self.reads: Counter[str] = Counter()
        self._counting = threading.Lock()

    def read(self, name: str) -> bytes:
        """The latest version's bytes of stored map ``name`` (counted); :class:`~twohr.mapstore.MapMissingError`
        (its text :func:`twohr.mapclient.no_map`) where the store has none."""
        try:
            data = self._store().read(name)
        except MapMissingError:
            raise MapMissingError(no_map(name)) from None
        with self._counting:
            self.reads[name] += 1
        return data

    def read_counts(self) -> dict[str, int]:
        """How often each stored map was read, by name."""
        with self._counting:
            return dict(self.reads)

    def stored(self, name: str, detector: DetectorConfig) -> MapFile | None:
        """Stored map ``name`` as a shared map starts from it (built with ``detector``); None where none is."""
        try:
            return read_map(self.read(name), detector=detector)
        except MapMissingError:
            return None

    def save(self, data: bytes, name: str, session_id: str | None) -> MapEntry:
        """Keep a map file's bytes as the next version of map ``name``, built by session ``session_id`` (None: the
        operator's); :class:`~twohr.mapstore.MapAccessError` for a session that does not save that map, or whose
        starter may not change it; :class:`~twohr.mapfile.MapFileError` for bytes that are not such a map."""
        control = None
        if session_id is not None:
            control = self.sessions.control(session_id)
            if control is None or name not in saved_names(control):
                raise MapAccessError(f"session {session_id!r} is no session of the map room that builds, extends or "
                                     f"shares map {name}")
        return self.save_for(data, name, control)

    def save_for(self, data: bytes, name: str, control: ControlMsg | None) -> MapEntry:
        """:meth:`save` on behalf of the session ``control`` started (None: the operator)."""
        builder, starter = (OPERATOR, OPERATOR) if control is None else (control.robot_id, control.started_by)
        grants = self._grants()
        by_session = {} if control is None else {"robot": builder, "session": control.session_id}

        def audited(entry: MapEntry) -> None:
            self.audit.record("map.save", STACK if control is None else starter, map=name, version=entry.version,
                              detail=f"owners {', '.join(entry.owners)}" + (
                                  f"; contributors {', '.join(entry.contributors)}" if entry.contributors else ""),
                              **by_session)

        try:
            return self._store().save(data, name, builder=builder, on_saved=audited,
                                      may_replace=lambda owners: may_change(starter, name, owners, grants))
        except MapAccessError as exc:
            self.audit.record("map.save", starter, map=name, detail=f"refused: {exc}", **by_session)
            raise

    def _grants(self) -> MapGrants:
        """The operator's grants as the file holds them now; an unreadable file grants nothing (and is logged)."""
        try:
            return MapGrants.load(self.settings.map_grants)
        except MapFileError as exc:
            log.error("%s: no robot holds a grant until it is fixed", exc)
            return MapGrants()

    def _store(self) -> MapStore:
        if self.store is None:
            raise TwohrError("this map room keeps no map store (twohr up --maps DIR)")
        return self.store
