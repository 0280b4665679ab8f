"""One pacer for replayed cameras (``twohr.rates.ReplayPacer``): by the recorded stamps at a speed (the source's
replays), or at a frame rate (``twohr camera --replay --rate``)."""

from __future__ import annotations

import threading
import time

import pytest

from twohr.rates import ReplayPacer


def paced(pacer: ReplayPacer, stamps: list[float], stop: threading.Event | None = None) -> list[float]:
    """When each frame went, in seconds after the first."""
    went = []
    for stamp in stamps:
        pacer.wait(stamp, stop)
        went.append(time.monotonic())
    return [t - went[0] for t in went]


def test_a_replay_goes_at_its_stamps_times_the_speed():
    went = paced(ReplayPacer(speed=2.0), [10.0, 10.1, 10.2, 10.4])
    assert [round(t, 2) for t in went[:1]] == [0.0]
    assert all(t >= due - 1e-3 for t, due in zip(went, [0.0, 0.05, 0.1, 0.2], strict=True)), went
    assert went[-1] < 0.2 + 0.5  # late frames go at once; lateness does not add up


def test_a_frame_rate_ignores_the_stamps():
    went = paced(ReplayPacer(fps=40), [0.0, 5.0, 5.0, 9.0, 9.0])
    assert all(t >= i / 40 - 1e-3 for i, t in enumerate(went)) and went[-1] < 0.1 + 0.5, went


def test_no_pace_a_restart_and_a_stop_wait_for_nothing():
    assert paced(ReplayPacer(), [0.0, 100.0])[-1] < 0.5 and paced(ReplayPacer(fps=0), [0.0, 0.0])[-1] < 0.5
    pacer = ReplayPacer(speed=1.0)
    pacer.wait(0.0)
    pacer.restart()
    assert paced(pacer, [50.0])[-1] == 0.0 and pacer.due(50.5) - time.monotonic() > 0.3  # 0.5 s after the restart
    stop = threading.Event()
    stop.set()
    started = time.monotonic()
    pacer.wait(80.0, stop)  # 30 s ahead, but the replay is stopped
    assert time.monotonic() - started < 1.0
    with pytest.raises(ValueError, match="not both"):
        ReplayPacer(speed=1.0, fps=30)
