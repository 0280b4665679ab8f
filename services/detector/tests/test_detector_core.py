"""The detector core on crafted score sets and on real frames with the real ONNX networks."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.spatial import cKDTree

from twohr.config import DetectorConfig
from twohr.dataset import RGBDSequence
from twohr.errors import ModelError
from twohr.models import BACKENDS, WHAT_IT_NEEDS, available_backends
from twohr_services.detector.classic import FASTDetector, ORBDetector, SIFTDetector
from twohr_services.detector.core import R2D2Detector, build_detector, choose_input_scale
from twohr_services.detector.filter import kmeans_1d, local_maxima, select_keypoints, subpixel_offsets, twohr_filter
from twohr_services.detector.images import network_size
from twohr_services.detector.networks import R2D2Network


def nearest_neighbours(points: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance from each point (N, 2) to its nearest target (M, 2), and that target's index."""
    distance, index = cKDTree(np.asarray(targets, np.float64)).query(np.asarray(points, np.float64), k=1)
    return distance, index


# ----------------------------------------------------------------------------- K-means and the 2HR filter


def test_kmeans_finds_three_separated_clusters():
    rng = np.random.default_rng(0)
    truth = np.repeat([0, 1, 2], [50, 80, 30])
    values = np.array([0.15, 0.55, 0.95])[truth] + rng.normal(0, 0.02, truth.size)
    order = rng.permutation(truth.size)
    labels, centres = kmeans_1d(values[order], 3)
    assert np.allclose(centres, [0.15, 0.55, 0.95], atol=0.01)
    assert np.array_equal(labels, truth[order])


def test_kmeans_is_deterministic_and_order_free():
    values = np.random.default_rng(1).uniform(0, 1, 3000)
    labels, centres = kmeans_1d(values, 4)
    shuffle = np.random.default_rng(2).permutation(values.size)
    labels_shuffled, centres_shuffled = kmeans_1d(values[shuffle], 4)
    assert np.array_equal(centres, centres_shuffled)
    assert np.array_equal(labels[shuffle], labels_shuffled)
    # uniform data: four equal-width intervals, so the centres sit near 1/8, 3/8, 5/8, 7/8
    assert np.allclose(centres, [0.125, 0.375, 0.625, 0.875], atol=0.03)


def test_kmeans_degenerate_inputs():
    labels, centres = kmeans_1d(np.array([]), 3)
    assert labels.size == 0 and centres.size == 0
    labels, _ = kmeans_1d(np.full(20, 0.8), 3)
    assert np.all(labels == labels[0])  # one distinct value: one non-empty cluster
    labels, centres = kmeans_1d(np.array([0.2, 0.9]), 5)  # k larger than the number of points
    assert labels.tolist() == [0, 1] and np.allclose(centres, [0.2, 0.9])


def _crafted_scores():
    """Reliability in three clusters (0.2, 0.6, 0.97) crossed with repeatability in two (0.3, 0.9)."""
    rng = np.random.default_rng(3)
    rel_cluster = np.tile([0, 1, 2], 40)
    rep_cluster = np.repeat([0, 1], 60)
    rel = np.array([0.2, 0.6, 0.97])[rel_cluster] + rng.uniform(-0.02, 0.02, 120)
    rep = np.array([0.3, 0.9])[rep_cluster] + rng.uniform(-0.04, 0.04, 120)
    return rel, rep, rel_cluster, rep_cluster


def test_filter_keeps_the_intersection_of_the_top_clusters():
    rel, rep, rel_cluster, rep_cluster = _crafted_scores()
    keep = twohr_filter(rel, rep, 3, 2, score_threshold=0.0)
    assert np.array_equal(keep, (rel_cluster == 2) & (rep_cluster == 1))
    assert keep.sum() == 20
    # a top-reliability point with low repeatability is out, and so is the reverse
    assert not keep[(rel_cluster == 2) & (rep_cluster == 0)].any()
    assert not keep[(rel_cluster == 1) & (rep_cluster == 1)].any()


def test_filter_threshold_applies_to_the_composite_score():
    rel, rep, rel_cluster, rep_cluster = _crafted_scores()
    threshold = 0.87
    keep = twohr_filter(rel, rep, 3, 2, score_threshold=threshold)
    expected = (rel_cluster == 2) & (rep_cluster == 1) & (rel * rep > threshold)
    assert np.array_equal(keep, expected)
    assert 0 < keep.sum() < 20  # the threshold cuts inside the intersection


def test_filter_cluster_counts_change_the_selection():
    rel, rep, rel_cluster, _ = _crafted_scores()
    # k=2 on reliability merges the 0.6 and 0.97 clusters... or splits them from 0.2: either way more survive
    assert twohr_filter(rel, rep, 2, 2, 0.0).sum() > twohr_filter(rel, rep, 3, 2, 0.0).sum()
    # k=1 means no clustering on that score: only the repeatability cluster and T remain
    assert np.array_equal(twohr_filter(rel, rep, 1, 1, 0.5), rel * rep > 0.5)


def test_filter_validates_and_handles_empty():
    assert twohr_filter(np.array([]), np.array([])).size == 0
    with pytest.raises(ValueError, match="differ in length"):
        twohr_filter(np.ones(3), np.ones(4))


def test_select_keypoints_floors_filter_and_top_n():
    rel, rep, _, _ = _crafted_scores()
    conf = DetectorConfig(features="r2d2", min_reliability=0.5, min_repeatability=0.5, max_keypoints=16)
    index = select_keypoints(rel, rep, conf)
    assert len(index) == 16
    assert np.all(rel[index] >= 0.5) and np.all(rep[index] >= 0.5)
    scores = rel[index] * rep[index]
    assert np.all(np.diff(scores) <= 0)
    assert scores.min() >= np.sort(rel * rep * (rel >= 0.5) * (rep >= 0.5))[-16]
    conf_2hr = conf.model_copy(update={"features": "2hr", "max_keypoints": 1000, "score_threshold": 0.0})
    floors = np.flatnonzero((rel >= 0.5) & (rep >= 0.5))
    expected = floors[twohr_filter(rel[floors], rep[floors], 3, 2, 0.0)]
    assert sorted(select_keypoints(rel, rep, conf_2hr).tolist()) == sorted(expected.tolist())
    assert len(expected) > 0


def test_local_maxima_finds_crafted_peaks_away_from_the_border():
    rep = np.zeros((40, 50), np.float32)
    rel = np.ones_like(rep)
    peaks = [(10, 10, 0.9), (10, 12, 0.8), (30, 40, 0.75), (1, 1, 0.99), (20, 25, 0.5)]
    for y, x, v in peaks:
        rep[y, x] = v
    ys, xs = local_maxima(rep, rel, min_repeatability=0.7, min_reliability=0.7, border=3)
    assert sorted(zip(ys.tolist(), xs.tolist(), strict=True)) == [(10, 10), (10, 12), (30, 40)]
    rel[30, 40] = 0.5
    ys, xs = local_maxima(rep, rel, 0.7, 0.7, 3)
    assert (30, 40) not in list(zip(ys.tolist(), xs.tolist(), strict=True))


def test_subpixel_offsets_recover_the_vertex_of_a_paraboloid():
    ys, xs = np.mgrid[0:20, 0:30].astype(np.float64)
    y0, x0 = 9.3, 14.6
    score = 1.0 - 0.05 * (xs - x0) ** 2 - 0.08 * (ys - y0) ** 2
    py, px = local_maxima(score.astype(np.float32), np.ones_like(score, np.float32), 0.5, 0.5, 1)
    assert (py.tolist(), px.tolist()) == ([9], [15])
    dy, dx = subpixel_offsets(score, py, px)
    assert py[0] + dy[0] == pytest.approx(y0, abs=1e-9)
    assert px[0] + dx[0] == pytest.approx(x0, abs=1e-9)


def test_subpixel_offsets_localise_gaussian_peaks_better_than_the_grid():
    rng = np.random.default_rng(3)
    ys, xs = np.mgrid[0:200, 0:200].astype(np.float64)
    centres = np.stack(np.meshgrid(np.arange(15, 190, 20), np.arange(15, 190, 20)), -1).reshape(-1, 2) + rng.uniform(
        -0.5, 0.5, (81, 2))
    score = np.zeros_like(xs)
    for cy, cx in centres:
        score = np.maximum(score, np.exp(-((ys - cy) ** 2 + (xs - cx) ** 2) / (2 * 1.5**2)))
    py, px = local_maxima(score.astype(np.float32), np.ones_like(score, np.float32), 0.5, 0.5, 2)
    assert len(py) == len(centres)
    dy, dx = subpixel_offsets(score, py, px)
    truth = centres[np.argmin(np.hypot(centres[None, :, 0] - py[:, None], centres[None, :, 1] - px[:, None]), 1)]
    grid_error = np.hypot(py - truth[:, 0], px - truth[:, 1])
    refined_error = np.hypot(py + dy - truth[:, 0], px + dx - truth[:, 1])
    assert np.all(np.abs(dy) <= 0.5) and np.all(np.abs(dx) <= 0.5)
    assert refined_error.max() < 0.1 < np.median(grid_error)


def test_subpixel_offsets_leave_flat_and_border_peaks_alone():
    score = np.zeros((5, 5))
    score[2, 1:4] = 1.0  # a ridge: flat along x
    score[0, 0] = 2.0  # a corner peak
    dy, dx = subpixel_offsets(score, np.array([2, 0]), np.array([2, 0]))
    assert dx.tolist() == [0.0, 0.0] and dy[1] == 0.0


def test_network_size_is_even():
    assert network_size(640, 480, 1.0) == (640, 480)
    assert network_size(640, 480, 0.5) == (320, 240)
    w, h = network_size(641, 479, 0.37)
    assert w % 2 == 0 and h % 2 == 0


# ----------------------------------------------------------------------------- real networks on real frames


@pytest.fixture(scope="module")
def real_frame(dev_sequence):
    return RGBDSequence(dev_sequence).read(120).rgb


@pytest.fixture(scope="module")
def default_keypoints(real_frame):
    return R2D2Detector(DetectorConfig(latency_budget_ms=None)).detect(real_frame)  # input_scale 0.75 anywhere


def test_2hr_on_a_real_frame(real_frame, default_keypoints):
    kp = default_keypoints
    conf = DetectorConfig()
    height, width = real_frame.shape[:2]
    assert 300 <= len(kp) <= conf.max_keypoints
    assert kp.descriptors.shape == (len(kp), 128) and kp.descriptors.dtype == np.float32
    assert np.allclose(np.linalg.norm(kp.descriptors, axis=1), 1, atol=1e-4)
    assert np.all((kp.xy[:, 0] >= conf.border) & (kp.xy[:, 0] <= width - 1 - conf.border))
    assert np.all((kp.xy[:, 1] >= conf.border) & (kp.xy[:, 1] <= height - 1 - conf.border))
    assert np.all(np.diff(kp.scores) <= 0)
    assert np.all(kp.reliability >= conf.min_reliability) and np.all(kp.repeatability >= conf.min_repeatability)
    assert np.all(kp.scores > conf.score_threshold)
    # keypoints spread over the image: every quadrant holds some
    quadrant = (kp.xy[:, 0] > width / 2).astype(int) * 2 + (kp.xy[:, 1] > height / 2)
    assert np.bincount(quadrant, minlength=4).min() >= 20


def test_2hr_is_a_subset_of_raw_r2d2(real_frame):
    twohr = R2D2Detector(DetectorConfig(input_scale=0.5))
    raw = R2D2Detector(DetectorConfig(features="r2d2", input_scale=0.5, max_keypoints=5000))
    maps = twohr.network(real_frame, (320, 240))
    kp_2hr = twohr.keypoints_from_maps(maps, (640, 480))
    kp_raw = raw.keypoints_from_maps(maps, (640, 480))
    assert len(kp_raw) > len(kp_2hr) > 50
    distance, nearest = nearest_neighbours(kp_2hr.xy, kp_raw.xy)
    assert np.all(distance < 1e-3)
    assert np.allclose(kp_2hr.descriptors, kp_raw.descriptors[nearest])


def test_sparse_descriptors_equal_the_exported_graph(real_frame):
    """The pruned graph + per-keypoint normalisation reproduces the dense exported output (faster2d2: stride 2)."""
    sparse = R2D2Network("faster2d2_WASF_N16", 2)
    dense = R2D2Network("faster2d2_WASF_N16", 2, sparse_descriptors=False)
    assert sparse.feature_stride == 2 and dense.feature_stride == 1
    maps = sparse(real_frame, (320, 240))
    ys, xs = local_maxima(maps.repeatability, maps.reliability, 0.5, 0.5, 2)
    # include the image corners, where the bilinear sampling clamps
    ys, xs = np.r_[ys, 0, 239, 0, 239], np.r_[xs, 0, 0, 319, 319]
    got, rel = maps.descriptors_at(ys, xs), maps.reliability.copy()
    reference = dense(real_frame, (320, 240))
    cosine = np.sum(got * reference.descriptors_at(ys, xs), axis=1)
    assert len(ys) > 100
    assert cosine.min() > 0.9999
    assert np.array_equal(rel, reference.reliability)


@pytest.mark.parametrize("model, stride", [("faster2d2_WASF_N16", 2), ("r2d2_WASF_N16", 1),
                                           ("r2d2_WASF_N16_int8", 1)])
def test_every_registered_network_gets_its_dense_normalisation_pruned(model, stride):
    import onnx

    from twohr.models import model_path
    from twohr_services.detector.networks import _prepare_model

    prepared = _prepare_model(str(model_path(model, kind="r2d2")), True)
    ops = {node.op_type for node in onnx.load_from_string(prepared.model).graph.node}
    assert "ReduceL2" not in ops and prepared.feature_stride == stride
    unchanged = _prepare_model(str(model_path(model, kind="r2d2")), False)
    assert "ReduceL2" in {node.op_type for node in onnx.load_from_string(unchanged.model).graph.node}


def test_int8_keypoints_agree_with_fp32(real_frame):
    fp32 = R2D2Detector(DetectorConfig(model="r2d2_WASF_N16", input_scale=0.5)).detect(real_frame)
    int8 = R2D2Detector(DetectorConfig(model="r2d2_WASF_N16_int8", input_scale=0.5)).detect(real_frame)
    assert len(fp32) > 100 and 0.7 < len(int8) / len(fp32) < 1.3
    distance, nearest = nearest_neighbours(int8.xy, fp32.xy)
    close = distance <= 2.0  # one network pixel at half resolution
    assert close.mean() > 0.8
    cosine = np.sum(int8.descriptors[close] * fp32.descriptors[nearest[close]], axis=1)
    assert np.median(cosine) > 0.95


def test_half_scale_keypoints_are_in_original_pixels(real_frame, default_keypoints):
    half = R2D2Detector(DetectorConfig(input_scale=0.5)).detect(real_frame)
    assert 100 <= len(half) < len(default_keypoints)
    assert half.xy[:, 0].max() > 480 and half.xy[:, 1].max() > 360  # not stuck in the 320x240 network frame
    distance, _ = nearest_neighbours(half.xy, default_keypoints.xy)
    assert np.median(distance) < 3.0


def test_the_input_scale_is_the_largest_whose_predicted_latency_fits():
    assert choose_input_scale(100, 0.75, 200, 0.75, 0.5) == 0.75
    assert choose_input_scale(280, 0.75, 200, 0.75, 0.5) == 0.625  # 194 ms predicted at 0.625
    assert choose_input_scale(300, 0.75, 200, 0.75, 0.5) == 0.5  # 208 ms at 0.625, 133 at 0.5
    assert choose_input_scale(2000, 0.75, 200, 0.75, 0.5) == 0.5  # none fits: the smallest
    assert choose_input_scale(300, 0.75, 200, 0.75, 0.55) == 0.625  # the ladder stops above the floor
    assert choose_input_scale(50, 0.5, 200, 1.0, 0.5) == 1.0  # timed at 0.5: 200 ms predicted at 1.0


def test_a_latency_budget_chooses_the_input_scale_once_per_image_size(real_frame):
    small = np.ascontiguousarray(real_frame[:240, :320])
    tight = R2D2Detector(DetectorConfig(latency_budget_ms=1e-3))
    keypoints = tight.detect(small)
    assert tight.input_scales == {(320, 240): 0.5}
    assert len(keypoints) > 20 and keypoints.xy[:, 0].max() > 240  # in image pixels, not the 160x120 network's
    tight.detect(real_frame)
    assert tight.input_scales == {(320, 240): 0.5, (640, 480): 0.5}
    loose = R2D2Detector(DetectorConfig(latency_budget_ms=1e6))
    fixed = R2D2Detector(DetectorConfig(latency_budget_ms=None, input_scale=0.625))
    for detector in (loose, fixed):
        detector.detect(small)
    assert loose.input_scales == {(320, 240): 0.75} and fixed.input_scales == {(320, 240): 0.625}
    half = R2D2Detector(DetectorConfig(input_scale=0.5)).detect(small)  # the scale the tight budget chose
    assert np.array_equal(half.xy, keypoints.xy)


def test_subpixel_keypoints_follow_a_shifted_image(real_frame):
    """Shift the image by 2 px: at input_scale 0.75 that is 1.5 network pixels, so grid keypoints move by 1 or 2
    network pixels (1.33 or 2.67 px) while refined ones should move by about the true 2 px."""
    shifted = np.ascontiguousarray(np.roll(real_frame, 2, axis=1))
    errors = {}
    for subpixel in (False, True):
        detector = R2D2Detector(DetectorConfig(subpixel=subpixel, latency_budget_ms=None))
        before, after = detector.detect(real_frame), detector.detect(shifted)
        distance, nearest = nearest_neighbours(before.xy + np.float32([2, 0]), after.xy)
        same = (distance < 1.5) & (before.xy[:, 0] > 20)
        assert same.sum() > 200
        errors[subpixel] = np.median(np.abs(after.xy[nearest[same], 0] - before.xy[same, 0] - 2.0))
        if subpixel:
            grid = R2D2Detector(DetectorConfig(subpixel=False, latency_budget_ms=None)).detect(real_frame)
            offset = np.abs(before.xy - grid.xy[nearest_neighbours(before.xy, grid.xy)[1]])
            assert offset.max() <= 0.5 * 640 / 480 + 1e-3 and np.median(offset) > 0.05
    assert errors[True] < 0.6 * errors[False]


@pytest.mark.parametrize("detector_class, dim, dtype", [(ORBDetector, 32, np.uint8), (FASTDetector, 32, np.uint8),
                                                        (SIFTDetector, 128, np.float32)])
def test_classical_baselines(real_frame, detector_class, dim, dtype):
    kp = detector_class(DetectorConfig(max_keypoints=800)).detect(real_frame)
    assert 100 <= len(kp) <= 800 + 20  # SIFT may return a few extra points at tied responses
    assert kp.descriptors.shape == (len(kp), dim) and kp.descriptors.dtype == dtype
    assert kp.binary == (dtype == np.uint8)


def test_build_detector_follows_the_config():
    assert isinstance(build_detector(DetectorConfig(features="orb")), ORBDetector)
    assert isinstance(build_detector(DetectorConfig(features="fast")), FASTDetector)
    assert isinstance(build_detector(DetectorConfig(features="sift")), SIFTDetector)
    assert isinstance(build_detector(DetectorConfig(features="r2d2")), R2D2Detector)


# ----------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("bad, message", [
    (np.zeros((48, 64, 3), np.float32), "uint8"),
    (np.zeros((48, 64), np.uint8), "shape"),
    (np.zeros((48, 64, 4), np.uint8), "shape"),
    (np.zeros((8, 8, 3), np.uint8), "too small"),
    ([[1, 2, 3]], "numpy"),
])
@pytest.mark.parametrize("features", ["2hr", "orb", "sift"])
def test_bad_images_raise_a_clear_value_error(bad, message, features):
    detector = build_detector(DetectorConfig(features=features, input_scale=0.25))
    with pytest.raises(ValueError, match=message):
        detector.detect(bad)


def test_bad_configuration_is_rejected():
    with pytest.raises(ValidationError):
        DetectorConfig(features="superpoint")
    with pytest.raises(ValidationError):
        DetectorConfig(input_scale=0)
    with pytest.raises(ValueError, match="2hr or r2d2"):
        R2D2Detector(DetectorConfig(features="orb"))


@pytest.mark.parametrize("backend", BACKENDS[1:])
def test_every_backend_gives_the_same_keypoints(real_frame, backend):
    """The CPU and GPU backends (``detector.backend``) agree with onnxruntime on the CPU, run where the machine
    has them (f32; a GPU's f16 within a pixel)."""
    if backend not in available_backends():
        pytest.skip(f"{backend} is not available here: it needs {WHAT_IT_NEEDS[backend]}")
    reference = R2D2Detector(DetectorConfig(backend="onnxruntime", latency_budget_ms=None)).detect(real_frame)
    keypoints = R2D2Detector(DetectorConfig(backend=backend, precision="f32", latency_budget_ms=None)).detect(
        real_frame)
    assert len(reference) > 300 and 0.95 < len(keypoints) / len(reference) < 1.05
    distance, nearest = nearest_neighbours(keypoints.xy, reference.xy)
    close = distance <= 1.0
    assert close.mean() > 0.95
    cosine = np.sum(keypoints.descriptors[close] * reference.descriptors[nearest[close]], axis=1)
    assert np.median(cosine) > 0.999


def test_a_backend_this_machine_lacks_is_refused_with_what_it_needs():
    from twohr.models import resolve_backend

    available = available_backends()
    assert "onnxruntime" in available and resolve_backend("auto") == available[0]
    assert available.index("onnxruntime") == len(available) - 1  # the CPU fallback comes last
    missing = [b for b in BACKENDS[1:] if b not in available]
    if not missing:
        pytest.skip("every backend is available on this machine")
    with pytest.raises(ModelError, match=f"{missing[0]} is not available here: it needs"):
        R2D2Detector(DetectorConfig(backend=missing[0]))
