"""Admission: a stack takes no more robots than it can serve at camera rate.

Each active session weighs what it asks of the stack, in robots at the nominal 30 Hz camera rate
(:func:`session_load`): a camera session 1, or ``rate / 30`` when it asks to be admitted at a lower rate
(``"rate": 15`` weighs 0.5); a replay its speed (``rate`` 1 = one camera in real time; 0 = as fast as the stack
goes, 1). A ``POST /sessions`` that would take the sum past the stack's capacity (``--max-robots``) gets 503 with a
``Retry-After`` header and a one-line reason, and the robots already running keep their share."""

from __future__ import annotations

import math
import os

from fastapi import HTTPException, status

from twohr import keys

from .sessions import SessionRequest, SessionTable

#: the camera rate one robot's share of the stack is sized for (Hz)
NOMINAL_HZ = 30.0
#: robots one core carries at NOMINAL_HZ with the default config: `twohr bench --live --robots N` on a 2-core
#: Xeon (AMX) posed 97 % of one robot's frames (1.0 core) and 41 % of each of two robots' (docs/fleet.md, "Capacity")
ROBOTS_PER_CORE = 0.5
#: what a refused client is told to wait before it asks again (s): a camera session has no end it could name
RETRY_AFTER_S = 30


def session_load(request: SessionRequest) -> float:
    """What one session asks of the stack, in robots at :data:`NOMINAL_HZ` (see the module docstring)."""
    if request.source == "camera":
        return min(1.0, request.rate / NOMINAL_HZ) if request.rate > 0 else 1.0
    return request.rate if request.rate > 0 else 1.0


def estimated_capacity(cores: int | None = None) -> float:
    """Robots this host's stack carries at camera rate, from its core count and :data:`ROBOTS_PER_CORE` (at least 1:
    a stack that cannot take one robot takes it anyway, degraded, rather than none)."""
    cores = cores or len(os.sched_getaffinity(0))
    return max(1.0, math.floor(cores * ROBOTS_PER_CORE * 2) / 2)


def parse_max_robots(value: str) -> float:
    """``--max-robots``: a count of robots (halves allowed: a robot at 15 Hz weighs half), or ``auto``
    (:func:`estimated_capacity`); :class:`~twohr.errors.ConfigError` in one line otherwise."""
    from twohr.errors import ConfigError

    if value == "auto":
        return estimated_capacity()
    try:
        count = float(value)
    except ValueError:
        count = 0.0
    if not count > 0 or not math.isfinite(count):
        raise ConfigError(f"--max-robots {value!r}: give a number of robots above 0, or auto")
    return count


def admitted_load(table: SessionTable) -> float:
    """The load of the sessions that hold a share of the stack now."""
    return sum(session_load(session.request) for session in table.active())


def least_loaded_tracker(trackers: set[str], table: SessionTable, always: bool = False) -> str:
    """The tracker replica a new session goes to: of ``trackers`` (the live ones), the one whose active sessions
    ask least of it (ties to the first by name); '' with none, or with one unless ``always``, where every tracker
    takes every session."""
    if len(trackers) < (1 if always else 2):
        return ""
    loads = dict.fromkeys(trackers, 0.0)
    for session in table.active():
        if session.tracker in loads:
            loads[session.tracker] += session_load(session.request)
    return min(sorted(loads), key=lambda replica: loads[replica])


def tracker_for(request: SessionRequest, trackers: set[str], table: SessionTable) -> str:
    """The tracker a new session goes to: a camera session to its robot's own tracker where that one is alive
    (``twohr camera --edge``: the robot's frames never reach the stack), else the least loaded of the stack's
    (:func:`least_loaded_tracker`; a robot's own tracker serves no other robot)."""
    own = keys.edge_replica(request.robot_id)
    if request.source == "camera" and own in trackers:
        return own
    return least_loaded_tracker(stack_trackers(trackers), table)


def stack_trackers(trackers: set[str]) -> set[str]:
    """Of live tracker replicas, the stack's: not a robot's own."""
    return {replica for replica in trackers if keys.edge_robot(replica) is None}


def admit(request: SessionRequest, table: SessionTable, capacity: float | None) -> None:
    """Raise 503 (with ``Retry-After``) when ``request`` would take the active sessions past ``capacity`` robots
    (None: no limit)."""
    if capacity is None:
        return
    load, wanted = admitted_load(table), session_load(request)
    if load + wanted > capacity + 1e-9:
        lower = (f"; or ask for \"rate\": {math.floor(NOMINAL_HZ * (capacity - load))} (Hz) to be admitted at a lower "
                 "rate" if request.source == "camera" and capacity - load >= 1 / NOMINAL_HZ else "")
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE,
                            f"the stack is full: it carries {capacity:g} robot{'' if capacity == 1 else 's'} at "
                            f"{NOMINAL_HZ:.0f} Hz "
                            f"(--max-robots) and runs {load:g}; try again in {RETRY_AFTER_S} s{lower}",
                            headers={"Retry-After": str(RETRY_AFTER_S)})
