"""The gateway's one registry of trackers (:class:`~twohr_services.gateway.trackers.Trackers`): where a session goes,
where a dead tracker's sessions go, and a robot's own tracker out of reach as a state. First on the registry and a
session table alone, then over HTTP and a real router, the trackers being stand-ins that hold liveliness tokens."""

from __future__ import annotations

import time

import httpx
import pytest

from twohr import keys
from twohr.bus import open_session
from twohr.keys import PIPELINE_SERVICES
from twohr.mapmodes import MapMode, MapRequest
from twohr_services.gateway.sessions import Session, SessionRequest, SessionTable
from twohr_services.gateway.settings import GatewaySettings
from twohr_services.gateway.trackers import (
    AWAY_DETAIL,
    PlacementRefused,
    TrackerKind,
    Trackers,
    TrackerState,
)


def _camera(robot: str, rate: float = 0, mode: MapMode | None = None) -> SessionRequest:
    return SessionRequest(source="camera", robot_id=robot, rate=rate,
                          map=MapRequest(name="lab", mode=mode) if mode else None)


def _placed(table: SessionTable, trackers: Trackers, request: SessionRequest) -> Session:
    session = Session(id=f"s{len(table.sessions)}", request=request, folder=None, tracker=trackers.place(request))
    table.add(session)
    return session


def test_sessions_go_to_their_robots_own_tracker_or_the_least_loaded_of_the_stacks():
    table = SessionTable()
    trackers = Trackers(table)
    trackers.came("t1")
    assert _placed(table, trackers, _camera("r1")).tracker == ""  # one stack tracker takes every session
    trackers.came("t2")
    trackers.came(keys.edge_replica("r9"))
    assert trackers.alive(TrackerKind.STACK) == {"t1", "t2"}
    assert trackers.alive(TrackerKind.OWN) == {"edge+r9"}
    table.sessions.clear()
    placed = [_placed(table, trackers, _camera(robot, rate)).tracker
              for robot, rate in (("r1", 0), ("r2", 15), ("r3", 15), ("r4", 0))]
    # r1 weighs 1 on t1; r2 and r3 0.5 each on t2; then 1.0 against 1.0: the first by name, t1
    assert placed == ["t1", "t2", "t2", "t1"], placed
    assert _placed(table, trackers, _camera("r9")).tracker == "edge+r9"
    replay = SessionRequest(sequence="dev", robot_id="r9")
    assert trackers.place(replay) in ("t1", "t2")  # a replay's frames come from the stack's source
    assert trackers.place(_camera("r9", mode=MapMode.SHARE)) == "edge+r9"
    with pytest.raises(PlacementRefused, match="robot r9 tracks itself .* but build needs the stack's tracker"):
        trackers.place(_camera("r9", mode=MapMode.BUILD))
    assert trackers.place(SessionRequest(source="camera", robot_id="r8")) in ("t1", "t2")  # no own tracker alive


def test_a_dead_stack_trackers_sessions_move_and_a_robots_own_trackers_wait_for_it():
    table = SessionTable()
    trackers = Trackers(table)
    for replica in ("t1", "t2", "t3", "edge+r9"):
        trackers.came(replica)
    on_t1 = [_placed(table, trackers, _camera(robot)) for robot in ("r1", "r2", "r3")]
    for session in on_t1:
        session.tracker = "t1"
    own = _placed(table, trackers, _camera("r9"))
    assert own.tracker == "edge+r9" and trackers.needs_stack(on_t1[0]) and not trackers.needs_stack(own)

    trackers.went("t1")
    rehomed = trackers.rehome("t1")
    assert rehomed.moved == on_t1 and not rehomed.failed and not rehomed.away
    assert [s.tracker for s in on_t1] == ["t2", "t3", "t2"] and [s.moves for s in on_t1] == [1, 1, 1]

    trackers.went("edge+r9")
    assert trackers.state("edge+r9") is TrackerState.GONE  # gone, not yet judged away (the grace runs)
    rehomed = trackers.rehome("edge+r9")
    assert rehomed.away == [own] and not rehomed.moved and not rehomed.failed
    assert trackers.state("edge+r9") is TrackerState.AWAY and own.tracker == "edge+r9" and own.detail == AWAY_DETAIL
    assert trackers.came("edge+r9") == [own]
    assert trackers.state("edge+r9") is TrackerState.ALIVE and own.detail == ""
    assert trackers.came("edge+r9") == []  # a token seen again changes nothing

    for replica in ("t2", "t3"):
        trackers.went(replica)
    rehomed = trackers.rehome("t2")
    assert rehomed.failed == [on_t1[0], on_t1[2]] and not rehomed.moved  # none alive to take them


@pytest.fixture
def stand_ins(bus_config):
    """Every pipeline service's token, held by a stand-in; and a robot's own tracker's, which the test drops."""
    session = open_session(bus_config)
    tokens = [session.liveliness().declare_token(keys.alive_key(name, "stand-in")) for name in PIPELINE_SERVICES]
    yield session
    for token in tokens:
        token.undeclare()
    session.close()


def test_an_own_trackers_absence_is_a_state_the_session_outlives(stand_ins, bus_config, serve_gateway, dev_sequence,
                                                                 tmp_path):
    """Robot r1's camera session goes to its own tracker; its token goes for longer than the grace: the session stays
    active, said away; back, the session goes on without a word."""
    own = stand_ins.liveliness().declare_token(keys.alive_key("tracker", keys.edge_replica("r1")))
    settings = GatewaySettings(data_roots=[dev_sequence.parent], recordings=tmp_path, bus=bus_config,
                               liveliness_grace=0.3)
    with serve_gateway(settings) as url, httpx.Client(base_url=url, timeout=30) as client:
        deadline = time.monotonic() + 30
        while (started := client.post("/sessions", json={"source": "camera", "robot_id": "r1", "record": False})
               ).status_code != 201:
            assert time.monotonic() < deadline, started.text
            time.sleep(0.1)
        session = started.json()
        assert session["tracker"] == "edge+r1", session
        own.undeclare()
        deadline = time.monotonic() + 20
        while (info := client.get(f"/sessions/{session['id']}").json())["detail"] != AWAY_DETAIL:
            assert time.monotonic() < deadline, info
            time.sleep(0.1)
        assert info["state"] in ("starting", "running") and info["tracker"] == "edge+r1" and info["moves"] == 0
        own = stand_ins.liveliness().declare_token(keys.alive_key("tracker", keys.edge_replica("r1")))
        deadline = time.monotonic() + 20
        while (info := client.get(f"/sessions/{session['id']}").json())["detail"] == AWAY_DETAIL:
            assert time.monotonic() < deadline, info
            time.sleep(0.1)
        assert info["state"] in ("starting", "running") and info["detail"] == "", info
        assert client.delete(f"/sessions/{session['id']}").status_code == 200
    own.undeclare()
