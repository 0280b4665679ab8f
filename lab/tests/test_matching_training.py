"""The torch network and its training loop: shapes, symmetry, ONNX parity, and a short real training run."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="the train extra (torch) is not installed")

from twohr.config import MatcherConfig  # noqa: E402
from twohr_lab.matching.data import LabelConfig, build_pair_set  # noqa: E402
from twohr_lab.matching.model import SiameseMatcherNet  # noqa: E402
from twohr_lab.matching.training import (  # noqa: E402
    TrainConfig,
    classification_metrics,
    export_onnx,
    predict,
    train_siamese,
)
from twohr_services.matcher.core import SiameseMatcher  # noqa: E402


def test_network_shapes_and_symmetry():
    torch.manual_seed(0)
    net = SiameseMatcherNet().eval()
    a, b = torch.randn(7, 128), torch.randn(5, 128)
    assert net.embed(a).shape == (7, 64)  # the paper's branch: Conv1d, max-pool to 64
    idx_a, idx_b = torch.tensor([0, 3, 6, 6]), torch.tensor([4, 0, 1, 2])
    scores = net(a, b, idx_a, idx_b)
    assert scores.shape == (4,) and torch.all((scores > 0) & (scores < 1))
    swapped = net(b, a, idx_b, idx_a)
    torch.testing.assert_close(scores, swapped)  # s(a, b) == s(b, a)
    torch.testing.assert_close(torch.sigmoid(net.logits(a[idx_a], b[idx_b])), scores)


def test_onnx_export_matches_torch(tmp_path):
    torch.manual_seed(1)
    net = SiameseMatcherNet().eval()
    path = export_onnx(net, tmp_path / "siamese.onnx", {"note": "test"})
    rng = np.random.default_rng(0)
    a = rng.standard_normal((40, 128)).astype(np.float32)
    b = rng.standard_normal((30, 128)).astype(np.float32)
    idx_a, idx_b = rng.integers(0, 40, 100), rng.integers(0, 30, 100)
    onnx_scores = SiameseMatcher(MatcherConfig(), model_file=path).score(a, b, idx_a, idx_b)
    with torch.no_grad():
        torch_scores = net(torch.from_numpy(a), torch.from_numpy(b), torch.from_numpy(idx_a),
                           torch.from_numpy(idx_b)).numpy()
    np.testing.assert_allclose(onnx_scores, torch_scores, atol=1e-5)


def test_classification_metrics():
    m = classification_metrics(np.array([0.9, 0.8, 0.2, 0.6]), np.array([1, 0, 1, 0], np.float32))
    assert m == {"accuracy": 0.25, "precision": pytest.approx(1 / 3), "recall": 0.5}


def test_a_short_training_run_on_real_pairs_lowers_the_loss(held_out_cache, held_out_pairs):
    pairs = build_pair_set(held_out_cache, held_out_pairs, LabelConfig(max_anchors=60), progress=False)
    counts = pairs.counts()
    assert counts["positives"] > 100 and counts["hard_negatives"] > 200
    conf = TrainConfig(epochs=2, batch_size=128, learning_rate=5e-3, seed=0)
    untrained = SiameseMatcherNet(channels=conf.channels, kernel_size=conf.kernel_size, hidden=conf.hidden)
    torch.manual_seed(conf.seed)
    _, loss_before = predict(untrained, pairs)
    result = train_siamese(pairs, pairs, conf, progress=False)
    scores, loss_after = predict(result.model, pairs)
    assert loss_after < 0.8 * loss_before
    assert loss_after < 0.5
    metrics = classification_metrics(scores, pairs.label)
    assert metrics["accuracy"] > 0.8
