"""The trackers the gateway places sessions on, in one registry (:class:`Trackers`): the stack's and robots' own
(``twohr camera --edge``, replica ``edge+<robot>``), which of them are alive (their liveliness tokens), where a new
session goes, where a dead tracker's sessions go, and which robots' own trackers are out of reach.

A camera session goes to its robot's own tracker where that one is alive (the robot's frames never reach the
stack), in a map mode an own tracker may use; any other session to the least loaded of the stack's trackers. When a
stack tracker dies, its sessions move to the least loaded of the others (or fail with none left); when a robot's own
tracker goes out of reach, its sessions stay (no other tracker has their frames) and are marked :attr:`away
<TrackerState.AWAY>` until it is back."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from enum import Enum

from twohr import keys
from twohr.errors import TwohrError

from .admission import session_load
from .sessions import Session, SessionRequest, SessionTable

#: what a session's detail says while its robot's own tracker is away: the robot tracks on
AWAY_DETAIL = "the robot's own tracker is out of reach (its link or its process): its poses come back with it"


class TrackerKind(str, Enum):
    STACK = "stack"  # one of the stack's trackers: any robot's sessions
    OWN = "own"  # a robot's own tracker (twohr camera --edge): that robot's camera session alone


class TrackerState(str, Enum):
    ALIVE = "alive"  # its liveliness token is up
    AWAY = "away"  # a robot's own tracker whose token went while it served a session: the session waits for it
    GONE = "gone"  # its token is down (a stack tracker's sessions move)


class PlacementRefused(TwohrError):
    """A session no live tracker may take as asked (a robot that tracks itself, in a mode only the stack's may)."""


def kind_of(replica: str) -> TrackerKind:
    return TrackerKind.OWN if keys.edge_robot(replica) is not None else TrackerKind.STACK


class Trackers:
    """The tracker replicas of one gateway, over its session ``table`` (the sessions assigned to each)."""

    def __init__(self, table: SessionTable) -> None:
        self.table = table
        self._alive: set[str] = set()
        self._away: set[str] = set()  # robots' own trackers that went while serving a session
        self._lock = threading.Lock()  # liveliness callbacks write, HTTP handlers and the monitor read

    def alive(self, kind: TrackerKind | None = None) -> set[str]:
        """The live tracker replicas (of ``kind``, every kind by default)."""
        with self._lock:
            return {replica for replica in self._alive if kind is None or kind_of(replica) is kind}

    def state(self, replica: str) -> TrackerState:
        with self._lock:
            if replica in self._alive:
                return TrackerState.ALIVE
            return TrackerState.AWAY if replica in self._away else TrackerState.GONE

    def came(self, replica: str) -> list[Session]:
        """A tracker's token came up; returns the active sessions it served while away (a robot's own tracker back
        in reach), which go on."""
        with self._lock:
            self._alive.add(replica)
            was_away = replica in self._away
            self._away.discard(replica)
        back = [s for s in self.table.active() if s.tracker == replica] if was_away else []
        for session in back:
            session.detail = ""
        return back

    def went(self, replica: str) -> None:
        """A tracker's token went (its sessions are moved or marked away once it stayed away: :meth:`rehome`)."""
        with self._lock:
            self._alive.discard(replica)

    def place(self, request: SessionRequest) -> str:
        """The tracker a new session goes to: a camera session to its robot's own tracker where that one is alive,
        else the least loaded of the stack's (:meth:`least_loaded`); :class:`PlacementRefused` for a robot that
        tracks itself and asks for a map mode only the stack's tracker serves."""
        own = keys.edge_replica(request.robot_id)
        if request.source != "camera" or own not in self.alive(TrackerKind.OWN):
            return self.least_loaded(self.alive(TrackerKind.STACK))
        if request.map is not None and not request.map.mode.edge_allowed:
            raise PlacementRefused(f"robot {request.robot_id} tracks itself (twohr camera --edge): it may localize in "
                                   f"or share a map, but {request.map.mode.value} needs the stack's tracker (twohr "
                                   "camera without --edge)")
        return own

    def least_loaded(self, trackers: set[str], always: bool = False) -> str:
        """Of ``trackers``, the one whose active sessions ask least of it (ties to the first by name); '' with none,
        or with one unless ``always``, where every tracker takes every session."""
        if len(trackers) < (1 if always else 2):
            return ""
        loads = dict.fromkeys(trackers, 0.0)
        for session in self.table.active():
            if session.tracker in loads:
                loads[session.tracker] += session_load(session.request)
        return min(sorted(loads), key=lambda replica: loads[replica])

    def needs_stack(self, session: Session) -> bool:
        """Whether ``session`` needs one of the stack's trackers (one on its robot's own tracker needs none)."""
        return kind_of(session.tracker) is TrackerKind.STACK

    def rehome(self, replica: str) -> Rehomed:
        """Tracker ``replica`` died: where each of its active sessions goes. A stack tracker's move to the least
        loaded of the others (now assigned to it, their moves counted), or fail where none is alive. A robot's own
        tracker's stay: its frames are the robot's and reach no other tracker; they are marked away
        (:data:`AWAY_DETAIL`) until it is back."""
        assigned = [s for s in self.table.active() if s.tracker == replica]
        if kind_of(replica) is TrackerKind.OWN:
            with self._lock:
                if assigned and replica not in self._alive:
                    self._away.add(replica)
            for session in assigned:
                session.detail = AWAY_DETAIL
            return Rehomed(away=assigned)
        others, done = self.alive(TrackerKind.STACK) - {replica}, Rehomed()
        for session in assigned:
            target = self.least_loaded(others, always=True)
            if not target:
                done.failed.append(session)
                continue
            session.tracker, session.moves = target, session.moves + 1
            done.moved.append(session)
        return done


@dataclass
class Rehomed:
    """What became of a dead tracker's sessions (:meth:`Trackers.rehome`)."""

    moved: list[Session] = field(default_factory=list)  # each now on another tracker (``session.tracker``)
    failed: list[Session] = field(default_factory=list)  # no other tracker alive
    away: list[Session] = field(default_factory=list)  # on a robot's own tracker: they wait for it
