"""The model registry against the real mirror in ../shared/models."""

import shutil
import subprocess
import sys

import pytest

from twohr import models
from twohr.errors import ModelError


@pytest.fixture
def isolated_cache(tmp_path, monkeypatch, model_mirror):
    monkeypatch.setenv("TWOHR_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("TWOHR_MODEL_MIRROR", str(model_mirror))
    return tmp_path / "cache" / "models"


def test_every_mirrored_model_verifies(model_mirror):
    mirrored = [s for s in models.registry().values() if (model_mirror / s.file).is_file()]
    assert len(mirrored) >= 10
    for spec in mirrored:
        models.verify_file(spec, model_mirror / spec.file)


def test_fetch_copies_and_verifies(isolated_cache):
    path = models.fetch("r2d2_WASF_N16_int8")
    assert path == isolated_cache / "r2d2_WASF_N16_int8.onnx"
    assert models.sha256_of(path) == models.get_spec("r2d2_WASF_N16_int8").sha256


def test_tampered_model_is_rejected(isolated_cache, tmp_path, monkeypatch, model_mirror):
    bad_mirror = tmp_path / "bad_mirror"
    bad_mirror.mkdir()
    shutil.copy(model_mirror / "yolov8n_320.onnx", bad_mirror / "yolov8n_320.onnx")
    with open(bad_mirror / "yolov8n_320.onnx", "r+b") as fh:
        fh.seek(1000)
        fh.write(b"\x00\x01\x02")
    monkeypatch.setenv("TWOHR_MODEL_MIRROR", str(bad_mirror))
    spec = models.get_spec("yolov8n_320")
    with pytest.raises(ModelError, match=spec.sha256):
        models.fetch("yolov8n_320")


def test_unknown_model_and_wrong_kind():
    with pytest.raises(ModelError, match="unknown model 'yolov99'"):
        models.get_spec("yolov99")
    with pytest.raises(ModelError, match="not r2d2"):
        models.get_spec("yolov8n", kind="r2d2")


def _twohr(*args, env=None):
    return subprocess.run([sys.executable, "-m", "twohr_app", *args], capture_output=True, text=True, env=env)


def test_cli_one_line_errors(tmp_path, model_mirror):
    import os

    bad_mirror = tmp_path / "bad"
    bad_mirror.mkdir()
    (bad_mirror / "yolov8n_320.onnx").write_bytes(b"tampered")
    env = dict(os.environ, TWOHR_CACHE=str(tmp_path / "cache"), TWOHR_MODEL_MIRROR=str(bad_mirror))
    result = _twohr("models", "fetch", "yolov8n_320", env=env)
    assert result.returncode == 1
    assert "fails its checksum" in result.stderr and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1

    result = _twohr("demo", "--sequence", str(tmp_path / "missing_sequence"))
    assert result.returncode == 2
    assert result.stderr.strip() == f"twohr: error: sequence folder not found: {tmp_path / 'missing_sequence'}"


def test_demo_runs_end_to_end(static_synthetic_sequence, tmp_path):
    """``make demo``'s command on a short synthetic sequence: the whole job, its outputs and a real trajectory."""
    import json

    from twohr.dataset import RGBDSequence
    from twohr.evaluation import evaluate, static_trajectory

    result = _twohr("demo", "--sequence", str(static_synthetic_sequence), "--out", str(tmp_path / "demo"))
    assert result.returncode == 0, result.stderr[-2000:]
    summary = json.loads((tmp_path / "demo" / "summary.json").read_text())
    sequence = RGBDSequence(static_synthetic_sequence)
    standing_still = evaluate(sequence.ground_truth(), static_trajectory(sequence.stamps))[0].ate.rmse
    assert summary["frames"] == 30 and summary["tracked_percent"] > 80, summary
    assert summary["ate"]["ate"]["rmse"] < standing_still / 3, (summary["ate"]["ate"], standing_still)
    assert (tmp_path / "demo" / "report.html").is_file() and (tmp_path / "demo" / "trajectory.txt").is_file()
