"""How a tracker shares its per-frame thread, and the host's cores, fairly between the robots it serves when it
cannot serve them all at their cameras' rates: :class:`FairShare` between its own robots, :class:`PeerShare`
between trackers on the same cores (``--shared-cores``). Each session keeps its share as evenly spaced frames
(:class:`twohr.rates.RateThinning`)."""

from __future__ import annotations

import collections
import time


class FairShare:
    """Equal shares of one per-frame thread for the robots it serves.

    It learns each session's camera rate (from its frames' stamps), how long the frames it tracks waited in its
    queue, and whether the sessions' keyframe jobs come back late (the maps' work starved of CPU). Once per
    ``window_s``, with two robots or more: while frames wait longer than ``high_ms`` (the thread does not keep up)
    or keyframe jobs come back late, every session's rate goes down, to the share of what the thread tracked at
    first, by a fifth after; while they wait less than ``low_ms`` it goes up by 1 Hz, until every camera has its
    full rate again. The same rate for every session, kept as evenly spaced frames
    (:class:`~twohr.rates.RateThinning`): equal shares, and none of the bursts that a queue dropping stale frames
    makes under overload. Sessions not seen for ``idle_s`` no longer
    count; one robot alone is never thinned (its queue's own drops serve it)."""

    def __init__(self, window_s: float = 1.0, high_ms: float = 60.0, low_ms: float = 20.0, idle_s: float = 2.0,
                 smoothing: float = 0.05) -> None:
        self.window_s, self.high_ms, self.low_ms, self.idle_s = window_s, high_ms, low_ms, idle_s
        self.smoothing = smoothing
        self.share_hz: float | None = None  # every session's rate, None: each its camera's
        self.waits: list[float] = []  # queue waits of the frames tracked in this window (ms)
        self.late = False  # a keyframe job came back late in this window
        self.window_start: float | None = None
        self.sessions: dict[str, list[float]] = {}  # session -> [camera period EMA, last stamp, last seen]

    def saw(self, session_id: str, stamp: float, now: float | None = None) -> None:
        """A frame of ``session_id`` arrived (stamp: its camera time)."""
        now = time.monotonic() if now is None else now
        known = self.sessions.get(session_id)
        if known is None:
            self.sessions[session_id] = [0.0, stamp, now]
            return
        gap = stamp - known[1]
        if 0 < gap < 1.0:
            known[0] = gap if known[0] == 0 else known[0] + self.smoothing * (gap - known[0])
        known[1], known[2] = stamp, now

    def tracked(self, waited_ms: float, keyframes_late: bool = False, now: float | None = None) -> None:
        """The thread tracked a frame that had waited ``waited_ms`` in its queue (``keyframes_late``: its session's
        latest keyframe job came back late); once a window, the share moves."""
        now = time.monotonic() if now is None else now
        self.window_start = now if self.window_start is None else self.window_start
        self.waits.append(waited_ms)
        self.late |= keyframes_late
        if now - self.window_start >= self.window_s:
            self._adjust(now)
            self.waits, self.late, self.window_start = [], False, now

    def _adjust(self, now: float) -> None:
        live = self._live(now)
        if len(live) < 2:
            self.share_hz = None
            return
        wait = sorted(self.waits)[len(self.waits) // 2]
        full = max(1.0 / period for period, _, _ in live.values())
        if wait > self.high_ms or self.late:
            tracked_hz = len(self.waits) / (now - self.window_start) / len(live)
            self.share_hz = max(1.0, tracked_hz if self.share_hz is None else 0.8 * self.share_hz)
        elif wait < self.low_ms and self.share_hz is not None:
            self.share_hz = None if self.share_hz + 1.0 >= full else self.share_hz + 1.0

    def _live(self, now: float) -> dict[str, list[float]]:
        return {s: v for s, v in self.sessions.items() if now - v[2] < self.idle_s and v[0] > 0}

    def forget(self, session_id: str) -> None:
        self.sessions.pop(session_id, None)

    def rate(self, session_id: str, now: float | None = None) -> float | None:
        """Frames per second ``session_id`` may have tracked now, or None while every camera gets its full rate."""
        live = self._live(time.monotonic() if now is None else now)
        if self.share_hz is None or session_id not in live or len(live) < 2:
            return None
        return min(1.0 / live[session_id][0], self.share_hz)


class PeerShare:
    """Fair shares between trackers on the same cores, each serving its own robots. Every tracker sees every
    robot's frames and poses go by. A robot it serves that is posed a larger fraction of its frames than the
    worst-served robot of the others is capped at that robot's fraction plus ``margin`` (of its own camera's rate,
    as evenly spaced frames), which frees the cores for that one; the worst-served robot is never capped, so shares
    only go up from there, and as its fraction rises, the cap rises with it. Fractions are over the latest
    ``window_s``, of robots posed for at least ``settle_s`` (a session's start, its first map, counts for none); a
    robot with no frame in the window no longer counts."""

    def __init__(self, window_s: float = 6.0, margin: float = 0.05, settle_s: float = 1.0) -> None:
        self.window_s, self.margin, self.settle_s = window_s, margin, settle_s
        self.seen: dict[str, tuple[collections.deque[float], collections.deque[float]]] = {}
        """robot -> times (monotonic s) of its latest frames, and of its latest poses"""
        self.first_posed: dict[str, float] = {}  # robot -> when it was first posed since it was last seen

    def _add(self, robot: str, which: int, now: float | None) -> None:
        self.seen.setdefault(robot, (collections.deque(), collections.deque()))[which].append(
            time.monotonic() if now is None else now)

    def framed(self, robot: str, now: float | None = None) -> None:
        """A frame of ``robot`` went by."""
        self._add(robot, 0, now)

    def posed(self, robot: str, now: float | None = None) -> None:
        """A pose of ``robot`` went by."""
        now = time.monotonic() if now is None else now
        self.first_posed.setdefault(robot, now)
        self._add(robot, 1, now)

    def rates(self, now: float | None = None) -> dict[str, tuple[float, float]]:
        """``robot -> (frames per second, posed fraction)`` of each robot with frames in the latest window, posed
        for at least ``settle_s``."""
        now = time.monotonic() if now is None else now
        rates = {}
        for robot, (frames, poses) in list(self.seen.items()):
            for times in (frames, poses):
                while times and now - times[0] > self.window_s:
                    times.popleft()
            if frames and now - self.first_posed.get(robot, now) >= self.settle_s:
                rates[robot] = (len(frames) / self.window_s, min(1.0, len(poses) / len(frames)))
            elif not frames and not poses:
                del self.seen[robot]
                self.first_posed.pop(robot, None)
        return rates

    def cap(self, robot: str, served: set[str], rates: dict[str, tuple[float, float]]) -> float | None:
        """The rate ``robot`` (one of ``served``, the robots of this tracker) may have tracked now, by ``rates``
        (:meth:`rates`), or None: no other robot is served worse."""
        others = [fraction for other, (_, fraction) in rates.items() if other not in served]
        if robot not in rates or not others:
            return None
        camera_hz, own = rates[robot]
        worst = min(others)
        if own <= worst or worst + self.margin >= 1.0:  # served no better than the others: no cap
            return None
        return max(1.0, (worst + self.margin) * camera_hz)
