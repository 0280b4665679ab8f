"""One command-line vocabulary, outputs outside the package, stamped results, and the lab's tracker studies."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

import numpy as np
import pytest

from twohr_app.cli import build_parser, main
from twohr_lab.tracking import accuracy, sensitivity, vo_bench

#: Fast settings for the synthetic sequences: ORB keypoints, no YOLO.
FAST = ["--set", "detector.features=orb", "--set", "yolo.enabled=false", "--set", "pipeline.synchronous=true"]


def _subparsers(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    """(command path, parser) of every subcommand, depth first."""
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _subparsers(sub, (*path, name))


def test_version_prints_the_installed_version():
    from importlib.metadata import version

    done = subprocess.run([sys.executable, "-m", "twohr_app", "--version"], capture_output=True, text=True)
    assert done.returncode == 0 and done.stdout.strip() == f"twohr {version('twohr')}"


@pytest.mark.parametrize("argv", [["models", "fetch", "--force", "siamese_2hr"],
                                  ["models", "fetch", "siamese_2hr", "--force"]])
def test_models_fetch_force_in_any_order(argv, capsys):
    assert main(argv) == 0
    assert capsys.readouterr().out.startswith("ok      siamese_2hr")


def test_no_command_writes_into_the_package_by_default():
    """Every output option of every subcommand defaults to nothing or to a folder under runs/ (or, in a study of
    ``twohr bench STUDY``, leaves the default to ``twohr bench``'s own option, checked here too)."""
    parsers = [*_subparsers(build_parser()), (("sensitivity",), sensitivity.build_parser())]
    seen = 0
    for path, parser in parsers:
        for action in parser._actions:
            if action.dest in ("out", "json", "model_out", "plot", "cache"):
                seen += 1
                assert action.default in (None, "runs/demo") or str(action.default).startswith("runs/") or (
                    path[0] == "bench" and action.default == argparse.SUPPRESS), (path, action.dest, action.default)
    assert seen >= 12


def test_frames_is_a_count_and_set_is_the_override_everywhere():
    """--frames never takes a stop index (no metavar STOP, no --stop), and no command takes --detector."""
    for path, parser in _subparsers(build_parser()):
        options = {opt for action in parser._actions for opt in action.option_strings}
        assert "--stop" not in options and "--detector" not in options, path
        for action in parser._actions:
            if "--frames" in action.option_strings:
                assert action.type in (int, None) or action.type.__name__ == "convert", path
                assert action.metavar != "STOP" and action.nargs is None, path
    with pytest.raises(SystemExit):
        main(["matcher", "eval", "--detector", "max_keypoints=5"])


def test_matcher_bench_takes_set_and_stamps_its_json(tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert main(["matcher", "bench", "--sequence", "", "--keypoints", "60", "--repeats", "1", "--runs", "1",
                 "--set", "matcher.threshold=0.3", "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["keypoints"] == [60, 60] and result["ms"]["mutual_nn"] > 0
    assert result["provenance"]["command"] == f"twohr matcher bench --sequence '' --keypoints 60 --repeats 1 " \
                                              f"--runs 1 --set matcher.threshold=0.3 --json {out}"
    assert len(result["provenance"]["commit"].split("+")[0]) == 40


def test_sensitivity_is_a_loop_over_run_sequence(synthetic_sequence, tmp_path):
    """Two settings of one parameter on a synthetic sequence with exact ground truth."""
    out = tmp_path / "sens"
    assert sensitivity.main(["--sequence", str(synthetic_sequence), "--frames", "30", *FAST, "--quiet",
                             "--sweep", "tracker.min_inliers=10,30", "--out", str(out)]) == 0
    rows = json.loads((out / "sensitivity.json").read_text())["rows"]
    assert [r["value"] for r in rows] == ["", "15 (default)", "10", "30"]
    assert all(r["ate_online"] < 0.03 and r["ate_refined"] < 0.06 and r["untracked_frames"] <= 3 for r in rows), rows
    table = (out / "sensitivity.md").read_text()
    assert table.startswith("Made by `python -m twohr_lab.tracking.sensitivity --sequence")
    assert "| tracker.min_inliers | median |" in table and "| all settings | median (min-max) |" in table
    assert sensitivity.main(["--sequence", str(synthetic_sequence), "--sweep", "min_inliers"]) == 2


def test_sensitivity_default_row_is_twohr_run(synthetic_sequence, tmp_path):
    """The defaults' row is exactly what `twohr run` reports for the same frames and settings."""
    from twohr.config import load_config
    from twohr.dataset import RGBDSequence

    sequence = RGBDSequence(synthetic_sequence)
    point = sensitivity.run_point(sequence, load_config(None, FAST[1::2]), 2, 2 + 20 * 2, 2)
    run_out = tmp_path / "run"
    assert main(["run", "--sequence", str(synthetic_sequence), "--start", "2", "--frames", "20", "--step", "2",
                 *FAST, "--quiet", "--out", str(run_out)]) == 0
    summary = json.loads((run_out / "summary.json").read_text())
    assert summary["frames"] == 20
    assert point["ate_refined"] == pytest.approx(summary["ate"]["ate"]["rmse"], abs=1e-12)
    assert point["ate_online"] == pytest.approx(summary["ate_online"]["ate"]["rmse"], abs=1e-12)


def test_accuracy_study_reports_every_figure_per_variant(static_synthetic_sequence, tmp_path):
    """Defaults, a later start and a config variant on a synthetic sequence with exact ground truth."""
    out = tmp_path / "accuracy"
    assert accuracy.main(["--sequence", str(static_synthetic_sequence), "--frames", "30", "--runs", "1", *FAST,
                          "--set", "tracker.depth_noise=0.005", "--variant", "from frame 5=--start=5",
                          "--variant", "integer keypoints=detector.subpixel=false", "--quiet",
                          "--out", str(out)]) == 0
    rows = json.loads((out / "accuracy.json").read_text())["rows"]
    assert [(r["variant"], r["start"]) for r in rows] == [("defaults", 0), ("from frame 5", 5),
                                                         ("integer keypoints", 0)]
    for row in rows:
        run = row["runs"][0]
        assert run["frames"] == 30 - row["start"] and run["tracked_percent"] > 90
        assert 0 < run["ate"] < 0.03 and run["ate_max"] >= run["ate"] and run["outliers"] == 0
        assert 0 < run["rpe_frame"] < 0.02 and 0 < run["jitter"] < 0.05  # the synthetic run is shorter than 1 s
        assert abs(run["sim3_scale"] - 1) < 0.1
    assert (out / "accuracy.png").stat().st_size > 10_000
    assert "| from frame 5 | 1 |" in (out / "accuracy.md").read_text()
    assert accuracy.main(["--sequence", str(static_synthetic_sequence), "--variant", "no equals sign"]) == 2


def test_vo_bench_compares_both_back_ends_on_the_same_frames(synthetic_sequence, tmp_path):
    out = tmp_path / "vo"
    assert vo_bench.main(["--sequence", str(synthetic_sequence), "--frames", "25", "--repeats", "1",
                          "--set", "detector.features=orb", "--set", "yolo.enabled=false", "--out", str(out)]) == 0
    result = json.loads((out / "bench.json").read_text())
    assert result["frames"] == 25 and result["repeats"] == 1
    assert np.isfinite(result["ratio_tracker_to_baseline"]) and result["tracker_ms_per_frame_median"] > 0
    assert result["tracker_ate_rmse"] < 0.05 and result["tracker_ate_rmse"] < result["baseline_vo_ate_rmse"]
    assert result["provenance"]["command"].startswith("python -m twohr_lab.tracking.vo_bench --sequence")
