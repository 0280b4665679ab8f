"""Where a tracker service's frames and sessions come from (a :class:`FrameInlet`): the stack's tracker takes every
robot's frames off the bus (:class:`BusInlet`); a robot's own tracker is fed its camera's frames in memory and
hears its own robot's sessions alone (``twohr_app.edge``)."""

from __future__ import annotations

from typing import Protocol

from twohr import keys
from twohr.messages import ControlMsg


class FrameInlet(Protocol):
    """The frames and sessions of one tracker service."""

    one_session: bool
    """it feeds one session at a time (a camera): a session that starts ends the one before"""

    def subscriptions(self) -> list[str]:
        """The keys its frames come on over the bus (none where they come in memory)."""

    def control_keys(self) -> list[str]:
        """The keys its sessions start and stop on."""

    def heard(self, control: ControlMsg, replica: str) -> None:
        """A session's control as it arrives off the bus, before it waits in the inbox behind the frame being
        tracked: where its robot's frames go is known from then on."""

    def takes(self, control: ControlMsg, replica: str) -> bool:
        """Whether the session ``control`` starts, moves or stops is tracker ``replica``'s."""

    def wants(self, robot: str) -> bool:
        """Whether a frame of ``robot`` that came over the bus is queued."""

    def started(self, control: ControlMsg) -> None:
        """A session started (or moved) here."""

    def stopped(self, session_id: str) -> None:
        """A session here ended."""


class BusInlet:
    """Every robot's frames and controls off the bus, as the stack's trackers take them: a session assigned to another
    tracker replica is that one's, and its robot's frames are not even queued here while it runs."""

    one_session = False

    def __init__(self) -> None:
        self.serving: dict[str, str] = {}  # session -> robot, of the sessions this replica serves
        self.elsewhere: dict[str, str] = {}  # session -> robot, of the sessions assigned to other tracker replicas

    def subscriptions(self) -> list[str]:
        return [keys.all_robots("frames")]

    def control_keys(self) -> list[str]:
        return [keys.all_robots(keys.CONTROL)]

    def heard(self, control: ControlMsg, replica: str) -> None:
        # on arrival: a first frame may keep the service thread a few seconds, and the other robot's frames that
        # came meanwhile were queued here and then ignored (38 of 60 in a test)
        if control.tracker in ("", replica):
            return
        if control.command in ("start", "move"):
            self.elsewhere[control.session_id] = control.robot_id
        else:
            self.elsewhere.pop(control.session_id, None)

    def takes(self, control: ControlMsg, replica: str) -> bool:
        return control.tracker in ("", replica)

    def wants(self, robot: str) -> bool:
        # a robot another tracker serves: its frames stay there (its controls still come in: they move it)
        return robot not in self.elsewhere.values() or robot in self.serving.values()

    def started(self, control: ControlMsg) -> None:
        self.serving[control.session_id] = control.robot_id
        self.elsewhere.pop(control.session_id, None)

    def stopped(self, session_id: str) -> None:
        self.serving.pop(session_id, None)
