"""`twohr run` end to end: a short real segment through the CLI, and bad frames that must not stop a run."""

import csv
import json
import shutil
import subprocess
import sys

import cv2
import numpy as np
import yaml

from twohr.config import load_config
from twohr.dataset import RGBDSequence
from twohr.trajectory import read_tum
from twohr_app.pipeline import run_sequence


def test_twohr_run_on_a_short_real_segment(dev_sequence, tmp_path):
    out = tmp_path / "run"
    result = subprocess.run([sys.executable, "-m", "twohr_app", "run", "--sequence", str(dev_sequence),
                             "--out", str(out), "--frames", "10", "--set", "detector.input_scale=0.5", "--quiet"],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    assert "ATE RMSE" in result.stdout
    trajectory = read_tum(out / "trajectory.txt")
    assert len(trajectory) == 10
    with open(out / "stats.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 10 and rows[0]["status"] == "init"
    assert all(int(r["kept"]) <= int(r["keypoints"]) for r in rows)
    assert sum(r["status"] == "tracking" for r in rows) >= 8
    summary = json.loads((out / "summary.json").read_text())
    # 10 frames (1/3 s) of a hand-held camera: the estimate must stay within a few centimetres
    assert summary["ate"]["ate"]["rmse"] < 0.05
    assert (out / "trajectory.png").stat().st_size > 10_000


def test_an_ablation_row_runs_from_the_product_command(dev_sequence, tmp_path):
    """``twohr run --preset orb``: the ablation table's ORB row, with --set still on top of it."""
    out = tmp_path / "orb"
    result = subprocess.run([sys.executable, "-m", "twohr_app", "run", "--sequence", str(dev_sequence), "--out",
                             str(out), "--frames", "10", "--preset", "orb", "--set", "tracker.final_ba_iterations=0",
                             "--quiet"], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert (config["detector"]["features"], config["yolo"]["enabled"], config["matcher"]["method"]) == (
        "orb", False, "mutual_nn")
    assert config["tracker"]["final_ba_iterations"] == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 10 and summary["ate"]["ate"]["rmse"] < 0.05
    bad = subprocess.run([sys.executable, "-m", "twohr_app", "run", "--sequence", str(dev_sequence), "--preset",
                          "fastest"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "invalid choice: 'fastest'" in bad.stderr and "Traceback" not in bad.stderr


def test_bad_frames_are_reported_not_fatal(synthetic_sequence, tmp_path):
    copy = tmp_path / "bad_frames"
    shutil.copytree(synthetic_sequence, copy)
    seq = RGBDSequence(copy)
    cv2.imwrite(str(seq.records[10].depth_path), np.zeros((240, 320), np.uint16))  # no depth at all
    seq.records[14].rgb_path.write_bytes(b"corrupt")  # unreadable image
    config = load_config(None, {"detector.features": "orb", "yolo.enabled": False, "matcher.method": "mutual_nn"})
    result = run_sequence(RGBDSequence(copy), config, stop=24, progress=False)
    assert result.skipped == [14]
    by_index = {s.index: s for s in result.stats}
    assert 14 not in by_index and len(by_index) == 23
    # a frame without depth still has 2-D matches to the map: PnP tracks it, and the stats say why
    assert by_index[10].with_depth == 0 and "no depth" in by_index[10].reason
    assert by_index[23].status in ("tracking", "relocalised")  # recovers after the bad frames


def test_every_keypoint_masked_is_reported(synthetic_sequence):
    from twohr_app.pipeline import FrontEnd, StageOutput

    seq = RGBDSequence(synthetic_sequence)
    config = load_config(None, {"detector.features": "orb", "matcher.method": "mutual_nn",
                                "pipeline.mode": "every_frame"})
    front_end = FrontEnd(load_config(None, {"detector.features": "orb", "yolo.enabled": False}))
    fronts = {}
    for frame in seq.frames(0, 8):
        mask = np.full(frame.depth.shape, frame.index == 5)  # a person fills the whole view of frame 5
        fronts[frame.index] = StageOutput(front_end(frame).keypoints, mask, int(frame.index == 5), 0.0, 0.0)
    result = run_sequence(seq, config, stop=8, progress=False, front_cache=fronts)
    statuses = [(stats.kept, stats.status) for stats in result.stats]
    assert statuses[5][0] == 0 and statuses[5][1] == "lost"
    assert statuses[7][1] in ("tracking", "relocalised")
