"""Admission: a stack takes no more robots than it can serve at camera rate.

Each active session weighs what it asks of the stack, in robots at the nominal 30 Hz camera rate
(:func:`session_load`): a camera session 1, or ``rate / 30`` when it asks to be admitted at a lower rate
(``"rate": 15`` weighs 0.5); a replay its speed (``rate`` 1 = one camera in real time; 0 = as fast as the stack
goes, 1). A ``POST /sessions`` that would take the sum past the stack's capacity (``--max-robots``) gets 503 with a
``Retry-After`` header and a one-line reason, and the robots already running keep their share."""

from __future__ import annotations

import math

from fastapi import HTTPException, status

from .sessions import SessionRequest, SessionTable

#: the camera rate one robot's share of the stack is sized for (Hz)
NOMINAL_HZ = 30.0
#: what a refused client is told to wait before it asks again (s): a camera session has no end it could name
RETRY_AFTER_S = 30


def session_load(request: SessionRequest) -> float:
    """What one session asks of the stack, in robots at :data:`NOMINAL_HZ` (see the module docstring)."""
    if request.source == "camera":
        return min(1.0, request.rate / NOMINAL_HZ) if request.rate > 0 else 1.0
    return request.rate if request.rate > 0 else 1.0


def parse_max_robots(value: str) -> float:
    """``--max-robots``: a count of robots (halves allowed: a robot at 15 Hz weighs half);
    :class:`~twohr.errors.ConfigError` in one line otherwise. ``auto`` means one thing wherever it is read: what
    ``twohr up`` measures on its host (``twohr_app.capacity``, the real networks timed); the gateway alone has no
    networks to time, so it refuses ``auto`` rather than guess from the cores."""
    from twohr.errors import ConfigError

    if value == "auto":
        raise ConfigError("--max-robots auto is measured by twohr up (python -m twohr_app.capacity prints this host's "
                          "figure); the gateway alone needs a number: give --max-robots N")
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
