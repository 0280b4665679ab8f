"""What may name a robot is said once (``twohr.ids``): the messages, the keys, the gateway's requests and the
fleet's robots all follow it."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from twohr import ids, keys, messages
from twohr.messages import PoseMsg


def test_one_pattern_and_one_list_of_reserved_names():
    assert messages.ID_PATTERN is ids.ID_PATTERN and keys.ROBOT_PATTERN is ids.ROBOT_PATTERN
    assert keys.RESERVED_ROBOT_IDS is ids.RESERVED_ROBOT_IDS and "maps" in ids.RESERVED_ROBOT_IDS
    assert ids.ROBOT_PATTERN.pattern == ids.ID_PATTERN[1:-1]


@pytest.mark.parametrize(("robot", "says"), [
    ("robot1", None), ("a" * 64, None), ("r_2-b", None),
    ("a" * 65, "invalid robot id"), ("-r", "invalid robot id"), ("a/b", "invalid robot id"),
    ("r1\n", "invalid robot id"), ("", "invalid robot id"), ("maps", "the map store's"),
])
def test_a_robot_id_is_checked_the_same_everywhere(robot, says):
    assert ids.robot_id_problem(robot) is None if says is None else says in ids.robot_id_problem(robot)
    if says is None:
        assert ids.check_robot_id(robot) == robot and keys.key(robot, "pose") == f"twohr/{robot}/pose"
        return
    with pytest.raises(ValueError, match=says):
        ids.check_robot_id(robot)
    with pytest.raises(ValueError, match=says):
        keys.key(robot, "pose")
    if robot != "maps":  # a message may speak of a map's robots on twohr/maps/...: the pattern alone holds there
        with pytest.raises(ValidationError):
            PoseMsg(session_id="s", robot_id=robot, frame_index=0, stamp=0.0, position=[0, 0, 0],
                    orientation=[0, 0, 0, 1], status="tracking")


def test_the_gateway_refuses_a_reserved_robot_id():
    from twohr_services.gateway.sessions import SessionRequest

    assert SessionRequest(sequence="seq", robot_id="r1").robot_id == "r1"
    with pytest.raises(ValidationError, match="the map store's"):
        SessionRequest(sequence="seq", robot_id="maps")
