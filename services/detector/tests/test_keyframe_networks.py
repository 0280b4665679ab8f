"""detector.model: every keyframe network loads through the registry and detects on a real frame; the INT8 network
is rebuilt byte for byte from the shipped ranges with its heads in float; ``auto`` keeps the fastest network that
meets the quality floor and says what it timed."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from pydantic import ValidationError
from scipy.spatial import cKDTree

from twohr.config import DetectorConfig
from twohr.dataset import RGBDSequence
from twohr.models import (
    KEYFRAME_NETWORKS,
    QUALITY_FLOOR_POINTS,
    QUALITY_REFERENCE,
    auto_candidates,
    fetch,
    get_spec,
    keyframe_network,
    registry,
    sha256_of,
)
from twohr.quantise import head_nodes
from twohr_services.detector.auto import AUTO_TIE, AutoChoice, auto_choice_key, keep_auto_choice, read_auto_choices
from twohr_services.detector.core import R2D2Detector
from twohr_services.detector.images import network_size
from twohr_services.detector.networks import _prepare_model

TIMED_AT = network_size(640, 480, DetectorConfig().min_input_scale)  # where auto times the candidates for VGA
REAL_FRAME = 120


@pytest.fixture(scope="module")
def real_frame(dev_sequence):
    return RGBDSequence(dev_sequence).read(REAL_FRAME).rgb


@pytest.fixture(scope="module")
def faster2d2_keypoints(keyframe_networks):
    return keyframe_networks.keypoints("faster2d2", REAL_FRAME)


def agreement(keypoints, reference) -> tuple[float, float]:
    """The share of ``keypoints`` within 1.5 px of a reference keypoint, and their median descriptor cosine."""
    distance, nearest = cKDTree(reference.xy).query(keypoints.xy, k=1)
    close = distance <= 1.5
    cosine = np.sum(keypoints.descriptors[close] * reference.descriptors[nearest[close]], axis=1)
    return float(close.mean()), float(np.median(cosine))


@pytest.mark.parametrize("name", list(KEYFRAME_NETWORKS))
def test_every_keyframe_network_loads_and_finds_keypoints_on_a_real_frame(name, keyframe_networks,
                                                                           faster2d2_keypoints):
    # built once per session (f32, no latency budget), its keypoints of the real frame detected once
    detector = keyframe_networks.detector(name)
    assert detector.model == KEYFRAME_NETWORKS[name] == get_spec(detector.model, "r2d2").name
    kp = keyframe_networks.keypoints(name, REAL_FRAME)
    assert 150 <= len(kp) <= 1500
    assert np.all(np.isfinite(kp.scores)) and np.allclose(np.linalg.norm(kp.descriptors, axis=1), 1, atol=1e-4)
    near, cosine = agreement(kp, faster2d2_keypoints)
    if name in ("faster2d2-int8", "faster2d2-int8-coarse"):  # faster2d2 quantised (heads moved): near-identical
        assert near > 0.85 and cosine > 0.98
    elif name == "student":  # distilled from faster2d2: most keypoints and descriptors follow it
        assert near > 0.4 and cosine > 0.8


def test_the_int8_network_is_rebuilt_from_the_shipped_ranges_byte_for_byte(tmp_path, monkeypatch):
    monkeypatch.setenv("TWOHR_CACHE", str(tmp_path))
    spec = get_spec("faster2d2_WASF_N16_int8")
    path = fetch(spec.name)  # builds it: faster2d2 from the mirror, quantised over the shipped ranges
    assert path.parent == tmp_path / "models" and sha256_of(path) == spec.sha256
    model = onnx.load(str(path))
    producers = {out: node for node in model.graph.node for out in node.output}

    def reads_int8(node) -> bool:
        return any(producers.get(name) is not None and producers[name].op_type == "DequantizeLinear"
                   for name in node.input)

    heads = set(head_nodes(model))
    trunk_convs = [n for n in model.graph.node if n.op_type == "Conv" and n.name not in heads]
    assert heads and len(trunk_convs) >= 7 and all(reads_int8(conv) for conv in trunk_convs)
    float_heads = [n for n in model.graph.node if n.name in heads and n.op_type in ("Softplus", "Div", "ReduceL2")]
    assert len(float_heads) >= 3 and not any(reads_int8(node) for node in float_heads)


def test_the_coarse_heads_network_is_built_byte_for_byte_with_its_heads_before_the_upsample(tmp_path, monkeypatch):
    monkeypatch.setenv("TWOHR_CACHE", str(tmp_path))
    spec = get_spec(keyframe_network("faster2d2-int8-coarse"))
    path = fetch(spec.name)  # builds INT8 from faster2d2, then moves its heads
    assert sha256_of(path) == spec.sha256
    # the graph the detector runs (descriptors read before the upsample, see _prepare_model)
    graph = onnx.load_from_string(_prepare_model(str(path), True).model).graph
    producers = {out: node for node in graph.node for out in node.output}
    upsamples = [n for n in graph.node if n.op_type == "Resize"]
    # only the heads' logits are upsampled (reliability 2 channels, repeatability 1), never the 128 features
    heads = [producers[n.input[0]] for n in upsamples]
    assert len(upsamples) == 2 and all(h.op_type == "Conv" for h in heads)
    weights = {init.name: init.dims for init in graph.initializer}
    assert sorted(weights[h.input[1]][0] for h in heads) == [1, 2]
    square = {producers[h.input[0]].name for h in heads}
    assert len(square) == 1 and producers[heads[0].input[0]].op_type == "Mul"


def test_auto_candidates_are_the_networks_within_the_quality_floor():
    models = registry()
    reference = models[QUALITY_REFERENCE].quality
    candidates = auto_candidates()
    # the reference, full R2D2, is never the fastest: left out while others meet the floor
    assert QUALITY_REFERENCE not in candidates and "faster2d2_WASF_N16" in candidates
    for name, spec in models.items():
        if spec.kind != "r2d2" or name == QUALITY_REFERENCE:
            continue
        meets = bool(spec.quality) and all(spec.quality[k] >= reference[k] - QUALITY_FLOOR_POINTS
                                           for k in ("rep", "prec"))
        assert (name in candidates) == meets, name
    quality = [models[n].quality["rep"] + models[n].quality["prec"] for n in candidates]
    assert quality == sorted(quality, reverse=True)


def test_auto_keeps_the_fastest_candidate_and_says_what_it_timed(real_frame, tmp_path):
    choices = tmp_path / "auto-choices.json"
    detector = R2D2Detector(DetectorConfig(model="auto", precision="f32"), auto_choices=choices)
    assert detector.model is None
    kp = detector.detect(real_frame)
    timings = detector.model_timings_ms
    # every candidate is timed, best quality first
    assert list(timings) == auto_candidates()
    assert len(timings) >= 2 and all(ms > 0 for ms in timings.values())
    assert detector.model == next(n for n, ms in timings.items() if ms <= AUTO_TIE * min(timings.values()))
    assert len(kp) > 150 and detector.input_scales[(640, 480)] >= DetectorConfig().min_input_scale
    # and keeps the choice for this host, under what it depends on
    kept = read_auto_choices(choices)
    assert list(kept) == [auto_choice_key(detector.conf, auto_candidates(), TIMED_AT)]
    assert kept[next(iter(kept))] == AutoChoice(model=detector.model, timings_ms=timings,
                                                timed_at=detector.model_timed_at)


def test_auto_uses_the_choice_kept_on_this_host_and_times_again_when_it_is_stale(real_frame, tmp_path):
    """Every process on a host must use one network (replicas, `twohr run` beside the services), whatever load each
    started under: a kept choice is used as it is, even one that a fresh timing would not make."""
    choices = tmp_path / "auto-choices.json"
    conf = DetectorConfig(model="auto", precision="f32")
    candidates = auto_candidates()
    slowest = candidates[0]  # faster2d2: about 3x the INT8 network's time in f32 on every CPU we measured
    kept = AutoChoice(model=slowest, timings_ms={n: 1.0 + i for i, n in enumerate(candidates)}, timed_at="2026-01-01")
    keep_auto_choice(choices, auto_choice_key(conf, candidates, TIMED_AT), kept)

    detector = R2D2Detector(conf, auto_choices=choices)
    kp = detector.detect(real_frame)
    assert (detector.model, detector.model_timings_ms, detector.model_timed_at) == (slowest, kept.timings_ms,
                                                                                   "2026-01-01")
    named = R2D2Detector(DetectorConfig(model=slowest, precision="f32", input_scale=detector.input_scales[(640, 480)],
                                        latency_budget_ms=None)).detect(real_frame)
    np.testing.assert_array_equal(kp.xy, named.xy)  # the very network it names

    # a choice for other model bytes (a new version) or another precision is not this one: timed again, both kept
    other = auto_choice_key(DetectorConfig(model="auto", precision="bf16"), candidates, TIMED_AT)
    choices.write_text(choices.read_text().replace(get_spec(slowest).sha256[:12], "0" * 12))
    keep_auto_choice(choices, other, kept)
    detector = R2D2Detector(conf, auto_choices=choices)
    detector.detect(real_frame)
    assert detector.model_timed_at != "2026-01-01" and min(detector.model_timings_ms.values()) > 1.0
    assert len(read_auto_choices(choices)) == 3 and read_auto_choices(choices)[other] == kept

    # a damaged file costs one warning and a timing, never the run
    choices.write_text("{not json")
    detector = R2D2Detector(conf, auto_choices=choices)
    assert len(detector.detect(real_frame)) > 150 and detector.model_timed_at != "2026-01-01"
    assert list(read_auto_choices(choices)) == [auto_choice_key(conf, candidates, TIMED_AT)]


def test_unknown_networks_are_refused_in_one_line():
    assert keyframe_network("faster2d2-int8") == "faster2d2_WASF_N16_int8"
    assert keyframe_network("r2d2_WASF_N16") == "r2d2_WASF_N16"
    with pytest.raises(ValidationError, match="unknown keyframe network 'superpoint'; choose auto, r2d2"):
        DetectorConfig(model="superpoint")
    with pytest.raises(ValidationError, match="unknown keyframe network 'yolov8n'"):
        DetectorConfig(model="yolov8n")  # registered, but not a keyframe network
