"""Fast checks of the student network (issue 41): a few distillation steps make the loss fall, and the
exported ONNX runs on onnxruntime (and through the detector's sparse-descriptor path) with finite outputs
of the documented shapes. About 20 s on one CPU thread."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

torch = pytest.importorskip("torch")
ort = pytest.importorskip("onnxruntime")

from twohr_lab.student.data import images_dir, list_images, models_dir, spread  # noqa: E402

TEACHER = models_dir() / "faster2d2_WASF_N16.onnx"
pytestmark = pytest.mark.skipif(not TEACHER.exists() or not images_dir().is_dir(),
                                reason="needs ../shared/models/faster2d2_WASF_N16.onnx and ../shared/images")


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    from twohr_lab.student.train import TrainConfig, train

    images = tmp_path_factory.mktemp("images")
    for i, path in enumerate(spread(list_images(images_dir()), 8)):
        shutil.copy(path, images / f"{i}{path.suffix}")
    out = tmp_path_factory.mktemp("run")
    conf = TrainConfig(batch=2, crop=96, lr=1e-2, save_every=5)
    summary = train(images, out, steps=15, teacher=TEACHER, conf=conf, eval_images=2, measure_latency=False,
                    progress=False)
    return out, summary, images, conf


def test_loss_falls(short_run):
    out, summary, _, _ = short_run
    history = [h for h in map(__import__("json").loads, (out / "log.jsonl").read_text().splitlines())]
    assert [h["step"] for h in history] == list(range(1, 16))
    first, first_rel, first_desc = history[0]["total"], history[0]["rel"], history[0]["desc"]
    last = float(np.mean([h["total"] for h in history[-3:]]))
    last_rel = float(np.mean([h["rel"] for h in history[-3:]]))
    last_desc = float(np.mean([h["desc"] for h in history[-3:]]))
    assert all(np.isfinite(h["total"]) for h in history)
    assert first > 1.5, first  # a fresh student is far from the teacher (measured: 2.52)
    assert last < 0.85 * first, (first, last)  # measured: 2.52 -> 1.96
    assert last_rel < 0.5 * first_rel, (first_rel, last_rel)  # measured: 0.41 -> 0.05
    assert last_desc < first_desc, (first_desc, last_desc)  # measured: 0.997 -> 0.91
    assert (out / "checkpoint.pt").exists() and (out / "model_card.md").exists() and (out / "loss.png").exists()
    assert summary["parameters"] < 484_387 / 2


def test_resume_continues_from_checkpoint(short_run, tmp_path):
    from twohr_lab.student.train import train

    out, _, images, conf = short_run
    run = tmp_path / "run"
    shutil.copytree(out, run)
    summary = train(images, run, steps=16, teacher=TEACHER, conf=conf, eval_images=1, measure_latency=False,
                    progress=False)
    assert summary["steps"] == 16
    assert len((run / "log.jsonl").read_text().splitlines()) == 16


@pytest.mark.parametrize("size", [(96, 128), (240, 320)])
def test_onnx_contract(short_run, size):
    out, _, _, _ = short_run
    height, width = size
    session = ort.InferenceSession(str(out / "student.onnx"), providers=["CPUExecutionProvider"])
    teacher = ort.InferenceSession(str(TEACHER), providers=["CPUExecutionProvider"])
    assert [i.name for i in session.get_inputs()] == [i.name for i in teacher.get_inputs()] == ["image"]
    assert [o.name for o in session.get_outputs()] == [o.name for o in teacher.get_outputs()]
    x = np.random.default_rng(0).standard_normal((1, 3, height, width)).astype(np.float32)
    desc, rel, rep = session.run(["descriptors", "reliability", "repeatability"], {"image": x})
    assert desc.shape == (1, 128, height, width)
    assert rel.shape == rep.shape == (1, 1, height, width)
    for array in (desc, rel, rep):
        assert np.isfinite(array).all()
    np.testing.assert_allclose(np.linalg.norm(desc, axis=1), 1.0, atol=1e-4)
    assert rel.min() >= 0 and rel.max() <= 1 and rep.min() >= 0 and rep.max() <= 1


def test_detector_sparse_path_recognises_the_export(short_run):
    """The detector's graph surgery finds the L2 normalisation after a 2x bilinear upsample (stride 2), as
    for faster2d2, and its per-keypoint descriptors equal the dense output."""
    from twohr_services.detector.networks import R2D2Maps, _prepare_model

    out, _, _, _ = short_run
    path = str(out / "student.onnx")
    prepared = _prepare_model(path, True)
    assert prepared.feature_stride == 2
    x = np.random.default_rng(1).standard_normal((1, 3, 64, 96)).astype(np.float32)
    raw = ort.InferenceSession(prepared.model, providers=["CPUExecutionProvider"]).run(None, {"image": x})
    dense = ort.InferenceSession(path, providers=["CPUExecutionProvider"]).run(["descriptors"], {"image": x})[0]
    names = [o.name for o in ort.InferenceSession(prepared.model, providers=["CPUExecutionProvider"]).get_outputs()]
    features = raw[names.index("descriptors")][0]
    assert features.shape == (128, 32, 48)
    ys, xs = np.array([5, 20, 40, 63]), np.array([7, 33, 50, 95])
    sparse = R2D2Maps(features, None, None, 2).descriptors_at(ys, xs)
    np.testing.assert_allclose(sparse, dense[0][:, ys, xs].T, atol=1e-4)
