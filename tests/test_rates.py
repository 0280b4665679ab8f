"""Frame rates: thinning a camera to a lower rate, fair shares of an overloaded per-frame thread, and of the cores
between trackers."""

from __future__ import annotations

from twohr.rates import RateThinning
from twohr_services.tracker.shares import FairShare, PeerShare


def test_thinning_keeps_evenly_spaced_frames_and_restarts_with_the_camera():
    at_15 = RateThinning(15)
    kept = [i for i in range(30) if at_15.keep(i / 30)]
    assert kept == list(range(0, 30, 2))
    at_10 = RateThinning(10)
    assert sum(at_10.keep(i / 30) for i in range(300)) == 100
    restarted = RateThinning(15)
    first = sum(restarted.keep(i / 30) for i in range(60))
    again = sum(restarted.keep(i / 30) for i in range(60))  # the driver restarted: stamps begin again
    assert (first, again) == (30, 30)


def feed(share: FairShare, sessions: list[str], seconds: float, capacity_hz: float) -> dict[str, float | None]:
    """Two-or-more 30 Hz cameras into a thread that tracks ``capacity_hz`` frames a second from one FIFO queue,
    each frame thinned by its session's share; a frame's wait is the queue ahead of it."""
    thinning = {session: None for session in sessions}
    t, queue, budget = 0.0, [], 0.0
    while t < seconds:
        for session in sessions:
            share.saw(session, t, now=t)
            rate = share.rate(session, now=t)
            if rate is not None:
                thinning[session] = thinning[session] or RateThinning(rate)
                thinning[session].period = 1 / rate
                if not thinning[session].keep(t):
                    continue
            queue.append(t)
        budget = min(budget + capacity_hz / 30, 2.0)
        while queue and budget >= 1:
            budget -= 1
            arrived = queue.pop(0)
            share.tracked(1000 * (t - arrived) + 1000 / capacity_hz, now=t)
        queue = queue[-12:]  # the stale ones are dropped
        t += 1 / 30
    return {session: share.rate(session, now=t) for session in sessions}


def test_an_overloaded_thread_is_shared_equally_and_only_when_overloaded():
    rates = feed(FairShare(), ["a", "b"], 30.0, capacity_hz=36)  # two 30 Hz robots, a thread for 36 frames/s
    assert rates["a"] == rates["b"] and 9 <= rates["a"] <= 18, rates  # at most the equal share of 36
    assert feed(FairShare(), ["a", "b"], 30.0, capacity_hz=90) == {"a": None, "b": None}  # it keeps up
    assert feed(FairShare(), ["a"], 30.0, capacity_hz=10) == {"a": None}  # one robot alone: the queue's own drops
    share = FairShare(idle_s=2.0)
    feed(share, ["a", "b"], 10.0, capacity_hz=36)
    share.saw("a", 19.9, now=19.9)
    assert share.rate("a", now=20.0) is None  # b went quiet: a has the thread again


def test_trackers_on_shared_cores_cap_only_the_better_served_robot():
    """Two robots at 30 Hz, each on its own tracker: ``a`` posed 24 of every 30 frames, ``b`` 15. Only ``a``'s
    tracker caps its robot, at ``b``'s fraction plus the margin (0.55 of 30 Hz); ``b`` is never capped; equal
    fractions cap nobody; a robot gone quiet for the window no longer counts, and one posed for less than the
    settling time (a session's start) does not count yet."""
    peers = PeerShare(window_s=3.0, margin=0.05, settle_s=3.0)
    for i in range(90):  # 3 s of both cameras
        t = i / 30
        for robot, posed_every in (("a", 30 / 24), ("b", 2)):
            peers.framed(robot, now=t)
            if i % posed_every < 1:
                peers.posed(robot, now=t)
    assert peers.rates(now=89 / 30) == {}  # both posed for less than the window yet
    for i in range(90, 180):
        t = i / 30
        for robot, posed_every in (("a", 30 / 24), ("b", 2)):
            peers.framed(robot, now=t)
            if i % posed_every < 1:
                peers.posed(robot, now=t)
    now = 179 / 30
    fractions = {robot: round(fraction, 1) for robot, (_, fraction) in peers.rates(now=now).items()}
    assert fractions == {"a": 0.8, "b": 0.5}, fractions  # 73 and 45 poses of the 91 frames in the window
    assert abs(peers.cap("a", {"a"}, peers.rates(now=now)) - 0.55 * 30) < 0.5
    assert peers.cap("b", {"b"}, peers.rates(now=now)) is None
    assert peers.cap("a", {"a", "b"}, peers.rates(now=now)) is None  # one tracker serving both: its FairShare's work
    assert peers.cap("a", {"a"}, peers.rates(now=now + 3.5)) is None  # nothing seen for longer than the window
    even = PeerShare(window_s=1.0, settle_s=1.0)
    for t in (0.0, 0.5, 1.0):
        for robot in ("a", "b"):
            even.framed(robot, now=t)
            even.posed(robot, now=t)
    assert len(even.rates(now=1.0)) == 2
    assert even.cap("a", {"a"}, even.rates(now=1.0)) is None and even.cap("b", {"b"}, even.rates(now=1.0)) is None
