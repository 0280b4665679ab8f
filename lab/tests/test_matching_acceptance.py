"""Issue #5 acceptance on held-out real frame pairs, plus the CLI shell around it."""

from __future__ import annotations

import numpy as np

from twohr.config import MatcherConfig
from twohr_app.cli import main
from twohr_lab.matching.cli import benchmark_matcher
from twohr_lab.matching.evaluation import evaluate_matchers
from twohr_services.matcher.core import build_matcher, mutual_nn, ratio_test


def test_siamese_precision_is_at_least_mutual_nn_at_equal_or_higher_matching_score(held_out_cache, held_out_pairs):
    """The registered model with the default config, on frames of the held-out 20 % it never saw."""
    matchers = {"mutual_nn": lambda a, b: mutual_nn(a, b), "siamese": build_matcher(MatcherConfig())}
    summaries, rows = evaluate_matchers(held_out_cache, held_out_pairs, matchers, progress=False)
    mnn, siamese = summaries["mutual_nn"], summaries["siamese"]
    assert mnn.frame_pairs == len(held_out_pairs) == 6
    assert mnn.matches_per_pair > 300  # real matching happened
    assert siamese.matching_score["3px"] >= mnn.matching_score["3px"], (siamese, mnn)
    assert siamese.mma["3px"] >= mnn.mma["3px"], (siamese, mnn)


def test_metrics_are_consistent_on_real_pairs(held_out_cache, held_out_pairs):
    summaries, rows = evaluate_matchers(
        held_out_cache, held_out_pairs, {"ratio": lambda a, b: ratio_test(a, b, 0.8)}, progress=False)
    s = summaries["ratio"]
    assert 0 < s.mma["1px"] <= s.mma["3px"] <= s.mma["5px"] <= 1
    assert 0 < s.matching_score["1px"] <= s.matching_score["3px"] <= s.matching_score["5px"] < 1
    for r in rows["ratio"]:
        assert r.correct["5px"] <= r.verifiable <= r.matches
        assert r.shared_view > 300 and 0 <= r.gt_repeatability <= 1


def test_benchmark_reports_medians_and_the_ratio_to_mutual_nn():
    result = benchmark_matcher(MatcherConfig(), num_keypoints=300, repeats=2)
    assert result["candidate_pairs"] == 900
    assert set(result["ms"]) >= {"mutual_nn", "ratio_test", "siamese", "siamese_head_onnx"}
    assert all(v > 0 for v in result["ms"].values())
    assert np.isclose(result["ratio_to_mutual_nn"]["mutual_nn"], 1.0)


def test_cli_reports_a_missing_sequence_in_one_line(tmp_path, capsys):
    code = main(["matcher", "eval", "--sequence", str(tmp_path / "missing"), "--cache", str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 2 and "sequence folder not found" in err and len(err.strip().splitlines()) == 1


def test_cli_rejects_gaps_that_are_not_multiples_of_the_step(tmp_path, capsys):
    code = main(["matcher", "eval", "--step", "2", "--deltas", "3", "--cache", str(tmp_path)])
    assert code == 2 and "multiples" in capsys.readouterr().err
