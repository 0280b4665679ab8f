"""The feature table, the parameter study, the benchmark and the ``twohr features`` CLI, on small real runs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from twohr.config import DetectorConfig
from twohr.dataset import RGBDSequence
from twohr_app.cli import main
from twohr_lab.features.bench import benchmark_detector, markdown_bench
from twohr_lab.features.plots import plot_study
from twohr_lab.features.quality import (
    FeatureTable,
    coverage,
    feature_table,
    kmeans_study,
    markdown_details,
    markdown_table,
    plan_pairs,
    restrict,
)


def test_plan_pairs():
    assert plan_pairs(30, (1, 5), step=10) == [(0, 1), (0, 5), (10, 11), (10, 15), (20, 21), (20, 25)]
    assert plan_pairs(30, (1, 5), step=10, start=5, stop=16) == [(5, 6), (5, 10)]


def test_coverage():
    assert coverage(np.zeros((0, 2)), (640, 480)) == 0.0
    assert coverage(np.array([[1.0, 1.0], [2.0, 2.0]]), (640, 480)) == pytest.approx(1 / 192)
    grid = np.mgrid[20:480:40, 20:640:40].reshape(2, -1).T[:, ::-1].astype(float)
    assert coverage(grid, (640, 480)) == 1.0


@pytest.fixture(scope="module")
def small_table(static_synthetic_sequence) -> FeatureTable:
    return feature_table(RGBDSequence(static_synthetic_sequence), ["ORB", "2HR"], deltas=(1, 3), step=10, stop=14,
                         progress=False)


def test_feature_table_on_a_static_synthetic_sequence(small_table):
    table = small_table
    assert [r.method for r in table.rows] == ["ORB", "2HR"]
    assert table.frames_detected == 6  # pairs (0 or 10, +1 or +3)
    for row in table.rows:
        assert row.by_delta["1"]["pairs"] == 2 and row.by_delta["3"]["pairs"] == 2
        assert row.keypoints_per_frame > 50 and row.ms_per_frame > 0
        # a static, exactly rendered room: most keypoints come back and most matches are right
        assert row.by_delta["1"]["rep"] > 60 and row.by_delta["1"]["prec"] > 80
        assert row.by_delta["1"]["rep_1to1"] <= row.by_delta["1"]["rep"]
        assert row.by_delta["1"]["rep_chance"] < row.by_delta["1"]["rep"] - 20  # 10 px off must cost repeats
        assert 0 <= row.clustered <= 1
    again = FeatureTable.model_validate_json(table.model_dump_json())
    assert again.rows[1].by_delta == table.rows[1].by_delta
    text = markdown_table(table)
    assert "| 2HR | R2D2 (128 float) |" in text and "%Rep Δ3" in text
    assert "chance %Rep Δ1" in markdown_details(table)


def test_restrict_summarises_a_subset_of_pairs(small_table):
    late = restrict(small_table, 10)
    assert all(p.a >= 10 for row in late.rows for p in row.pairs)
    assert late.rows[0].by_delta["1"]["pairs"] == 1 and late.rows[0].by_delta["3"]["pairs"] == 1
    assert late.rows[0].by_delta["1"]["rep"] == pytest.approx(
        100 * late.rows[0].pairs[0].repeated / late.rows[0].pairs[0].shared)


def test_kmeans_study_small_grid(static_synthetic_sequence, tmp_path):
    grid = {"score_threshold": [0.0, 0.9], "reliability_clusters": [1, 3]}
    full_resolution = DetectorConfig(input_scale=1.0)  # the study is defined on the full-resolution maps
    result = kmeans_study(RGBDSequence(static_synthetic_sequence), full_resolution, deltas=(2,), step=10, stop=13,
                          grid=grid, progress=False)
    assert [(p.parameter, p.value) for p in result.points] == [("score_threshold", 0.0), ("score_threshold", 0.9),
                                                              ("reliability_clusters", 1.0),
                                                              ("reliability_clusters", 3.0)]
    counts = {(p.parameter, p.value): p.keypoints_per_frame for p in result.points}
    assert counts[("score_threshold", 0.9)] < counts[("score_threshold", 0.0)]
    assert counts[("reliability_clusters", 1.0)] >= counts[("reliability_clusters", 3.0)]
    assert result.raw_r2d2.keypoints_per_frame >= max(counts.values())
    assert all(p.by_delta["2"]["pairs"] == 2 for p in result.points)
    png = plot_study(result, tmp_path / "study.png", {"score_threshold": 0.5})
    assert png.stat().st_size > 10_000


def test_benchmark_detector_reports_medians(static_synthetic_sequence):
    image = RGBDSequence(static_synthetic_sequence).read(0).rgb
    result = benchmark_detector(image, models=["faster2d2_WASF_N16"], scales=[0.5], runs=1, filter_runs=3,
                                progress=False)
    (net,) = result["networks"]
    assert net["input"] == [160, 120] and net["keypoints"] > 0
    assert net["network_ms"] > 0 and net["baseline_dense_ms"] > 0 and np.isfinite(net["ratio_to_baseline"])
    assert result["filter"]["points"] == 5000 and result["filter"]["ms"] > 0
    assert "faster2d2_WASF_N16 | 160×120" in markdown_bench(result)
    json.dumps(result)


def test_cli_eval_writes_the_table(static_synthetic_sequence, tmp_path, capsys):
    code = main(["features", "eval", "--sequence", str(static_synthetic_sequence), "--frames", "6", "--step", "5",
                 "--deltas", "1", "--methods", "FAST", "2HR", "--input-scale", "0.5", "--split-at", "3",
                 "--out", str(tmp_path)])
    assert code == 0
    assert {p.name for p in tmp_path.iterdir()} == {"feature_table.md", "feature_table.json", "feature_table.png",
                                                    "stamp.json"}
    stamp = json.loads((tmp_path / "stamp.json").read_text())
    assert stamp["command"].startswith("twohr features eval --sequence") and "--split-at 3" in stamp["command"]
    assert (tmp_path / "feature_table.md").read_text().startswith(f"Made by `{stamp['command']}` at commit")
    assert "| FAST | ORB (256 bit), at FAST corners |" in capsys.readouterr().out
    assert json.loads((tmp_path / "feature_table.json").read_text())["detector"]["input_scale"] == 0.5


@pytest.mark.parametrize("argv, message", [
    (["features", "eval", "--sequence", "/no/such/sequence"], "sequence folder not found"),
    (["features", "study", "--model", "yolov8n", "--frames", "3"], "yolov8n"),
    (["features", "eval", "--set", "detector.score_threshold=2"], "score_threshold"),
    (["features", "bench", "--frame", "100000"], "outside the sequence"),
])
def test_cli_user_errors_are_one_line(argv, message, capsys, dev_sequence):
    code = main(argv)
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert message in err and "Traceback" not in err and len(err.splitlines()) == 1


@pytest.mark.parametrize("argv, message", [
    (["features", "eval", "--step", "0"], "positive integer"),
    (["features", "study", "--start", "-5"], "frame number"),
    (["features", "eval", "--threshold", "0"], "positive number"),
    (["features", "bench", "--scales", "half"], "positive number"),
])
def test_cli_rejects_bad_numbers(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err
