"""``twohr up --max-robots auto``: the robots a host carries, measured on it (one keyframe job and one frame, with
the real networks on rendered frames) and kept per CPU, or taken from what ``twohr bench --fleet`` found."""

from __future__ import annotations

import math

from twohr_app import capacity
from twohr_app.capacity import KEYFRAME_JOBS_PER_S, USABLE_SHARE, auto_capacity, keep_bench, robots_for


def test_the_formula_counts_half_robots_and_never_admits_none():
    per_robot = KEYFRAME_JOBS_PER_S * 0.2 + 30 * 0.01
    assert robots_for(16, 0.2, 0.01) == math.floor(2 * 16 * USABLE_SHARE / per_robot) / 2
    assert robots_for(64, 0.2, 0.01) > robots_for(16, 0.2, 0.01) > robots_for(2, 0.2, 0.01)
    assert robots_for(2, 1.0, 0.05) == 1.0  # a host too slow for one robot still serves one, degraded


def test_auto_measures_once_keeps_the_figure_and_prefers_the_fleet_bench(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    said: list[str] = []
    first = auto_capacity(say=said.append)
    assert said and "measuring" in said[0]
    assert first.source == "measured at start"
    # a keyframe job runs three networks and a bundle adjustment: tens to hundreds of ms on any CPU we know of
    assert 20 < first.keyframe_ms < 5000 and 0 < first.frame_ms < first.keyframe_ms, first
    assert first.robots == robots_for(first.cores, first.keyframe_ms / 1000, first.frame_ms / 1000) >= 1
    assert capacity.cache_file() == tmp_path / "twohr" / "capacity.json" and capacity.cache_file().is_file()

    again = auto_capacity(say=said.append)  # kept: not measured again
    assert len(said) == 1 and again == first

    keep_bench(3)
    assert auto_capacity(say=said.append).robots == 3.0 and len(said) == 1
    # the kept file is private, and a figure edited out of bounds is not taken: measured again
    assert capacity.cache_file().stat().st_mode & 0o777 == 0o600
    for bad in ("1e6", "Infinity"):
        kept = capacity.cache_file().read_text()
        capacity.cache_file().write_text(kept.replace('"robots": 3.0', f'"robots": {bad}'))
        assert capacity.kept_capacity().source == "measured at start", bad
        capacity.cache_file().write_text(kept)
