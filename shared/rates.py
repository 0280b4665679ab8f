"""Frame rates: when a replayed camera's next frame is due, which frames of a camera to keep at a lower rate, and
a camera's frames relayed into a session at its admitted rate. (How a tracker shares its per-frame thread between
robots is the tracker's: ``twohr_services.tracker.shares``.)"""

from __future__ import annotations

import threading
import time


class ReplayPacer:
    """Holds a replayed camera's frames back until each is due, counted from the first frame's wait: by the recorded
    stamps at ``speed`` times the recorded speed (1 real time, 2 twice as fast), or (``fps``) one frame every
    ``1/fps`` seconds, whatever the stamps say. Neither (0) does not wait. A frame that is late goes at once, and the
    ones after it keep their own times: lateness does not add up."""

    def __init__(self, speed: float = 0.0, fps: float = 0.0) -> None:
        if speed and fps:
            raise ValueError("pace a replay by its stamps (speed) or at a frame rate (fps), not both")
        self.speed, self.fps = speed, fps
        self.started: float | None = None  # monotonic time the first frame (since a restart) went
        self.first_stamp = 0.0
        self.frames = 0  # frames since then

    def restart(self) -> None:
        """The next frame is due at once; the ones after it at the pace from there."""
        self.started = None

    def due(self, stamp: float = 0.0) -> float | None:
        """The monotonic time the frame stamped ``stamp`` is due (the next frame, at a frame rate), or None: no
        pace. Each call counts one frame."""
        if self.speed <= 0 and self.fps <= 0:
            return None
        if self.started is None:
            self.started, self.first_stamp, self.frames = time.monotonic(), stamp, 0
        after = (stamp - self.first_stamp) / self.speed if self.speed > 0 else self.frames / self.fps
        self.frames += 1
        return self.started + after

    def wait(self, stamp: float = 0.0, stop: threading.Event | None = None) -> None:
        """Return when the frame stamped ``stamp`` is due, or at once when ``stop`` is set."""
        due = self.due(stamp)
        delay = 0.0 if due is None else due - time.monotonic()
        if delay <= 0:
            return
        if stop is not None:
            stop.wait(delay)
        else:
            time.sleep(delay)


class RateThinning:
    """Which frames of a camera to keep at ``rate`` Hz: one per ``1/rate`` of camera time (a frame up to a quarter
    period early counts as on time, so a 30 Hz camera at 15 Hz gives every other frame, evenly spaced); a camera
    whose stamps go back in time (its driver restarted) or jump ahead starts again. ``rate`` may change as it goes
    (:attr:`period`)."""

    def __init__(self, rate: float) -> None:
        self.period = 1.0 / rate
        self.due: float | None = None

    def keep(self, stamp: float) -> bool:
        if self.due is not None and (stamp < self.due - 2 * self.period or stamp > self.due + 2 * self.period):
            self.due = None  # back in time, or a long gap: a new start
        if self.due is not None and stamp < self.due - self.period / 4:
            return False
        self.due = (self.due if self.due is not None else stamp) + self.period
        return True


#: a camera session's status reports the frames relayed so far every this many frames
RELAY_STATUS_EVERY = 15


class CameraRelay:
    """A camera's frames (``twohr/<robot>/camera`` messages) into one session, at the rate the session was admitted
    at (``rate`` Hz, 0 = the camera's): numbered, stamped with the session's id, the images untouched. The stack's
    source relays a camera session this way, and a robot's own tracker its camera (``twohr camera --edge``)."""

    def __init__(self, session_id: str, rate: float = 0.0) -> None:
        self.session_id = session_id
        self.thinning = RateThinning(rate) if rate > 0 else None
        self.sent = 0

    def relay(self, payload: bytes) -> bytes | None:
        """The session's frame message for this camera frame, or None for a frame above the admitted rate."""
        from .messages import FrameMsg, decode, relayed_frame

        if self.thinning is not None and not self.thinning.keep(decode(payload, FrameMsg, only=())[0].stamp):
            return None
        relayed = relayed_frame(payload, self.session_id, self.sent)
        self.sent += 1
        return relayed

    @property
    def status_due(self) -> bool:
        """Whether the frames relayed so far are due on the session's status (every :data:`RELAY_STATUS_EVERY`)."""
        return self.sent > 0 and self.sent % RELAY_STATUS_EVERY == 0
