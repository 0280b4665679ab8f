"""What may name a robot (or a session): the id pattern, the names it may not take, and the check of both."""

from __future__ import annotations

import re

#: a robot's or a session's id, without anchors: letters, digits, '_' and '-', at most 64, a letter or digit first
ROBOT_ID = r"[A-Za-z0-9][A-Za-z0-9_-]{0,63}"
#: :data:`ROBOT_ID` anchored, for a pydantic ``Field(pattern=...)`` (it matches the whole value)
ID_PATTERN = rf"^{ROBOT_ID}$"
#: :data:`ROBOT_ID` compiled; use ``fullmatch`` (no newline, no path separator)
ROBOT_PATTERN = re.compile(ROBOT_ID)
#: robot ids that name something else under ``twohr/``, and what they name
RESERVED_ROBOT_IDS = {"maps": "the map store's (twohr/maps/...)"}
#: ROS 2 names a fleet's robot may not take (its ROS 2 namespace ``/<robot>`` would be the topic): ROS 2's global
#: topics, which the stack's nodes publish, and the root of the ros2 bridge's default camera input (``/camera/...``)
ROS2_RESERVED_NAMES = ("tf", "tf_static", "clock", "rosout", "parameter_events", "diagnostics", "camera")


def robot_id_problem(robot_id: str) -> str | None:
    """Why ``robot_id`` cannot name a robot on the bus (not the pattern, or a reserved name), or None if it can."""
    if not isinstance(robot_id, str) or not ROBOT_PATTERN.fullmatch(robot_id):
        return (f"invalid robot id {robot_id!r}: use letters, digits, '_' or '-' (at most 64), starting with a "
                "letter or digit")
    if robot_id in RESERVED_ROBOT_IDS:
        return f"invalid robot id {robot_id!r}: it is {RESERVED_ROBOT_IDS[robot_id]}, choose another"
    return None


def check_robot_id(robot_id: str) -> str:
    """``robot_id`` if it can name a robot on the bus; ValueError (one line) otherwise."""
    problem = robot_id_problem(robot_id)
    if problem is not None:
        raise ValueError(problem)
    return robot_id
