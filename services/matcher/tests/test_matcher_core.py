"""The matcher core on its own: Siamese inference, mutual-best selection, fallbacks, bad input, the registry."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest

from twohr.config import MatcherConfig
from twohr.models import get_spec, model_path, sha256_of
from twohr_services.matcher.core import (
    SiameseMatcher,
    build_matcher,
    knn_candidates,
    mutual_best,
    mutual_nn,
    ratio_test,
)


def unit_vectors(rng: np.random.Generator, n: int, dim: int = 128) -> np.ndarray:
    v = rng.standard_normal((n, dim)).astype(np.float32)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def noisy_copy(rng: np.random.Generator, desc: np.ndarray, sigma: float) -> np.ndarray:
    v = desc + rng.normal(0, sigma, desc.shape).astype(np.float32)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_registered_model_loads_with_its_checksum():
    spec = get_spec("siamese_2hr", kind="siamese")
    path = model_path("siamese_2hr", kind="siamese")
    assert spec.bundled and path.name == "siamese_2hr.onnx"
    assert sha256_of(path) == spec.sha256
    assert path.stat().st_size < 200_000  # small enough to ship in the repo
    matcher = SiameseMatcher()
    assert matcher.descriptor_dim == 128


def test_knn_candidates_are_the_k_nearest():
    rng = np.random.default_rng(0)
    a, b = unit_vectors(rng, 50), unit_vectors(rng, 80)
    idx_a, idx_b = knn_candidates(a, b, 3)
    assert len(idx_a) == 150
    dist = np.linalg.norm(a[:, None] - b[None], axis=2)
    expected = np.sort(np.argsort(dist, axis=1)[:, :3], axis=1)
    np.testing.assert_array_equal(np.sort(idx_b.reshape(50, 3), axis=1), expected)
    np.testing.assert_array_equal(idx_a.reshape(50, 3), np.repeat(np.arange(50)[:, None], 3, axis=1))


def test_mutual_best_keeps_pairs_that_win_both_ways():
    idx_a = np.array([0, 0, 1, 1, 2])
    idx_b = np.array([5, 6, 5, 7, 7])
    scores = np.array([0.9, 0.2, 0.8, 0.3, 0.4])
    # a0 -> b5 (0.9) and b5's best is a0: kept; a1's best is b5 but b5 prefers a0; a2 -> b7 and b7's best is a2
    np.testing.assert_array_equal(mutual_best(idx_a, idx_b, scores), [0, 4])


def test_siamese_matches_are_mutual_best_unique_and_above_tau():
    rng = np.random.default_rng(1)
    a = unit_vectors(rng, 300)
    b = noisy_copy(rng, a[rng.permutation(300)], 0.05)
    conf = MatcherConfig(candidates=4, threshold=0.3)
    matcher = SiameseMatcher(conf)
    m = matcher.match(a, b)
    assert len(m) > 0
    assert len(np.unique(m.idx_a)) == len(m) and len(np.unique(m.idx_b)) == len(m)
    assert np.all(m.scores >= conf.threshold)
    idx_a, idx_b = knn_candidates(a, b, conf.candidates)
    scores = matcher.score(a, b, idx_a, idx_b)
    for ia, ib, s in zip(m.idx_a, m.idx_b, m.scores, strict=True):
        assert s == pytest.approx(scores[idx_a == ia].max(), abs=1e-6)
        assert s == pytest.approx(scores[idx_b == ib].max(), abs=1e-6)


def test_siamese_recovers_a_permutation_of_slightly_noisy_descriptors():
    rng = np.random.default_rng(2)
    a = unit_vectors(rng, 400)
    perm = rng.permutation(400)
    b = noisy_copy(rng, a[perm], 0.02)  # b[j] is a[perm[j]]
    m = SiameseMatcher(MatcherConfig(threshold=0.5)).match(a, b)
    correct = np.mean(perm[m.idx_b] == m.idx_a)
    assert len(m) >= 360 and correct >= 0.99


def test_empty_inputs_give_no_matches():
    rng = np.random.default_rng(3)
    matcher = SiameseMatcher()
    empty = np.zeros((0, 128), np.float32)
    for a, b in ((empty, unit_vectors(rng, 10)), (unit_vectors(rng, 10), empty), (empty, empty)):
        m = matcher.match(a, b)
        assert len(m) == 0 and m.idx_a.dtype == np.int64
    assert len(matcher.score(empty, empty, np.zeros(0, np.int64), np.zeros(0, np.int64))) == 0


def test_a_single_candidate_is_fine():
    rng = np.random.default_rng(4)
    a = unit_vectors(rng, 5)
    m = SiameseMatcher(MatcherConfig(candidates=3, threshold=0.0)).match(a, a[:1])
    assert len(m) == 1 and m.idx_b[0] == 0 and m.idx_a[0] == 0


def test_binary_descriptors_fall_back_to_hamming_mutual_nn(caplog):
    rng = np.random.default_rng(5)
    image = cv2.GaussianBlur(rng.integers(0, 255, (240, 320), dtype=np.uint8), (3, 3), 0)
    orb = cv2.ORB_create(300)
    _, desc_a = orb.detectAndCompute(image, None)
    _, desc_b = orb.detectAndCompute(np.roll(image, 3, axis=1), None)
    with caplog.at_level(logging.WARNING):
        m = SiameseMatcher().match(desc_a, desc_b)
    expected = mutual_nn(desc_a, desc_b)
    np.testing.assert_array_equal(m.idx_a, expected.idx_a)
    np.testing.assert_array_equal(m.idx_b, expected.idx_b)
    assert len(m) > 50
    assert "Hamming" in caplog.text


@pytest.mark.parametrize("bad_a, bad_b, message", [
    (np.zeros(128, np.float32), np.zeros((3, 128), np.float32), "2-D"),
    (np.zeros((3, 128), np.float32), np.zeros((3, 64), np.float32), "differ"),
    (np.zeros((3, 64), np.float32), np.zeros((3, 64), np.float32), "128-D"),
])
def test_bad_descriptor_arrays_raise_clear_errors(bad_a, bad_b, message):
    with pytest.raises(ValueError, match=message):
        SiameseMatcher().match(bad_a, bad_b)


def test_build_matcher_returns_each_method():
    rng = np.random.default_rng(6)
    a = unit_vectors(rng, 100)
    b = noisy_copy(rng, a, 0.05)
    for method, reference in (("mutual_nn", mutual_nn(a, b)), ("ratio", ratio_test(a, b, 0.7))):
        m = build_matcher(MatcherConfig(method=method, ratio=0.7))(a, b)
        np.testing.assert_array_equal(m.idx_a, reference.idx_a)
        np.testing.assert_array_equal(m.idx_b, reference.idx_b)
    m = build_matcher(MatcherConfig(method="siamese"))(a, b)
    assert np.mean(m.idx_a == m.idx_b) > 0.95 and len(m) > 90


class _ShapeLog:
    """The real onnxruntime session, noting the input shapes of every call."""

    def __init__(self, session) -> None:
        self.session, self.calls = session, []

    def run(self, outputs, feeds):
        self.calls.append({name: value.shape for name, value in feeds.items()})
        return self.session.run(outputs, feeds)


def test_a_whole_map_query_runs_in_bounded_chunks_with_unchanged_matches():
    """A relocalisation against 20k map descriptors: no onnxruntime call sees more than the cap, same matches."""
    rng = np.random.default_rng(7)
    world = unit_vectors(rng, 20_000)
    frame = noisy_copy(rng, world[rng.choice(20_000, 1500, replace=False)], 0.03)
    matcher = SiameseMatcher()
    cap = matcher.conf.max_pairs_per_call
    reference = SiameseMatcher(MatcherConfig(max_pairs_per_call=100_000)).match(frame, world)  # one call
    matcher.session = log = _ShapeLog(matcher.session)
    m = matcher.match(frame, world)
    assert len(log.calls) == -(-1500 * matcher.conf.candidates // cap)
    assert all(max(shape[0] for shape in call.values()) <= cap for call in log.calls)
    np.testing.assert_array_equal(m.idx_a, reference.idx_a)
    np.testing.assert_array_equal(m.idx_b, reference.idx_b)
    np.testing.assert_array_equal(m.scores, reference.scores)
    assert len(m) > 1200
    log.calls.clear()
    matcher.match(frame[:300], world[:2000])  # below the cap: one call with the whole arrays, as ever
    assert log.calls == [{"desc_a": (300, 128), "desc_b": (2000, 128), "idx_a": (900,), "idx_b": (900,)}]


def test_knn_candidates_of_a_whole_map_query_need_bounded_memory():
    """The (Na, Nb) distance matrix of a 1500 x 20k query would be 120 MB; it is built a block at a time."""
    import tracemalloc

    rng = np.random.default_rng(8)
    a, b = unit_vectors(rng, 1500), unit_vectors(rng, 20_000)
    tracemalloc.start()
    try:
        idx_a, idx_b = knn_candidates(a, b, 3)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 50e6
    small_a, small_b = knn_candidates(a[:200], b, 3, block=30_000)  # one row of A at a time: the same candidates
    np.testing.assert_array_equal(small_a, idx_a[:600])
    np.testing.assert_array_equal(small_b, idx_b[:600])


def test_a_match_query_of_ragged_or_too_many_descriptors_is_refused_before_any_matrix():
    from twohr.messages import MessageError
    from twohr_services.matcher.service import MAX_MATCH_PAIRS, check_pair

    rows = np.zeros((10, 128), np.float32)
    check_pair(rows, rows)
    for a, b in ((rows, rows[:, :64]), (rows, rows.astype(np.float64)), (rows[0], rows),
                 (np.zeros((MAX_MATCH_PAIRS // 1000 + 1, 1), np.float32), np.zeros((1000, 1), np.float32))):
        with pytest.raises(MessageError):
            check_pair(a, b)
