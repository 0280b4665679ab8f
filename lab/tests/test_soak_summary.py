"""The soak's summary: RSS growth after a warm-up and FPS drift, scaled to the soak's length."""

from twohr_lab.bench.steps.camera_sessions import soak_summary


def _row(minutes: int, growth_per_minute: float) -> dict:
    samples = [(t, 200.0 + growth_per_minute * t / 60) for t in range(0, minutes * 60 + 1, 10)]
    return {"rss_mib": {"tracker": samples, "matcher": [(t, 150.0) for t, _ in samples]},
            "fps_per_minute": [30.0] * (minutes - 1) + [27.0]}


def test_a_short_soak_still_measures_growth_after_its_warm_up():
    summary = soak_summary(_row(5, growth_per_minute=2.0), minutes=5)  # warm-up and windows: 1 minute
    assert summary["rss_growth_after_warmup_mib"] == {"tracker": 8.0, "matcher": 0.0}
    assert summary["fps_first_window"] == 30.0 and summary["fps_last_window"] == 27.0
    assert summary["fps_change_percent"] == -10.0


def test_a_long_soak_warms_up_for_five_minutes():
    summary = soak_summary(_row(60, growth_per_minute=1.0), minutes=60)
    assert summary["rss_growth_after_warmup_mib"]["tracker"] == 55.0  # minute 5 to 60
    assert summary["fps_first_window"] == 30.0 and summary["fps_last_window"] == 29.4  # last 5 minutes
