"""The keyframe-policy benchmark's table and its refusals (the runs themselves are `twohr run`, tested elsewhere)."""

from __future__ import annotations

import pytest

from twohr_lab.tracking import keyframe_policy


def _row(run: int, ate: float, online: float, keyframes: int, fps: float, condition: str = "2c") -> dict:
    return {"run": run, "sequence": "dev", "config": "default", "condition": condition, "ate": ate,
            "ate_online": online, "keyframes": keyframes, "live_keyframes": keyframes - 5, "jobs": keyframes,
            "shed": 3, "fps": fps, "scale": 0.75, "network": "faster2d2", "tracked": 95.0}


def test_the_table_gives_medians_with_their_runs_and_the_online_ratio():
    rows = [_row(1, 0.0150, 0.0180, 50, 40.0), _row(2, 0.0140, 0.0170, 52, 42.0), _row(3, 0.0160, 0.0200, 51, 41.0),
            _row(1, 0.0200, 0.0300, 49, 25.0, "1c")]
    lines = keyframe_policy.table(rows).splitlines()
    assert len(lines) == 4  # header, rule, one line per cell
    two_cores = lines[2].split(" | ")
    assert two_cores[3] == "0.0150 (0.0150, 0.0140, 0.0160)" and two_cores[4] == "0.0180"
    assert two_cores[5] == "1.20" and two_cores[6] == "50–52 (45–47)" and two_cores[8] == "41.0"
    assert "1 core (`taskset -c 0`)" in lines[3] and "| 1.50 |" in lines[3]


def test_it_refuses_an_unknown_condition_and_a_missing_variant(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        keyframe_policy.main(["--sequences", "dev", "--conditions", "3c", "--out", str(tmp_path)])
    assert exit_info.value.code == 2 and "unknown condition 3c" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        keyframe_policy.main(["--sequences", "backwards", "--backwards", str(tmp_path / "none"), "--out",
                              str(tmp_path)])
    assert exit_info.value.code == 2 and "twohr_lab.tracking.backwards" in capsys.readouterr().err
    assert not (tmp_path / "rows.tsv").exists()
