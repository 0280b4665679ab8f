"""The `twohr run` report: the marked trajectory, the per-frame timeline and report.html, on real frames."""

import csv
import json
import re
import shutil
import subprocess
import sys

import numpy as np

from twohr.trajectory import read_tum
from twohr_app.report import flags_for, frame_flags
from twohr_services.tracker.stages import FrameStats


def test_run_writes_a_linked_html_report(viewed_run):
    """The report of :func:`viewed_run` (``tests/conftest.py``: ``twohr run`` on 90 real frames, whose live view
    test_run_view.py reads)."""
    out, frames = viewed_run["out"], viewed_run["frames"]
    assert viewed_run["returncode"] == 0, viewed_run["stderr"]
    summary = json.loads((out / "summary.json").read_text())
    page = (out / "report.html").read_text()
    links = set(re.findall(r'(?:href|src)="([^"]+)"', page))
    assert {"trajectory.png", "timeline.png", "stats.csv", "summary.json", "config.yaml", "trajectory.txt",
            "trajectory_online.txt"} <= links
    assert all((out / link).is_file() for link in links)
    assert f"{summary['ate']['ate']['rmse']:.4f} m" in page and f"<td>{summary['frames']}</td>" in page
    for image in ("trajectory.png", "timeline.png"):
        assert (out / image).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and (out / image).stat().st_size > 30_000
    with open(out / "stats.csv") as fh:
        rows = list(csv.DictReader(fh))
    keyframes = sum(r["keyframe"] == "True" for r in rows)
    assert 1 <= keyframes < frames and len(rows) == summary["frames"] == frames


def test_flags_follow_the_frames_by_stamp():
    def stats(index, status="tracking", keyframe=False, mask=0.0):
        return FrameStats(index=index, stamp=100.0 + index / 30, status=status, keypoints=10, kept=10, with_depth=10,
                          matches=10, inliers=8, keyframe=keyframe, dynamic_objects=0, mask_percent=mask,
                          ms_detector=0, ms_yolo=0, ms_tracker=1, ms_total=1)

    rows = [stats(0, "init", keyframe=True), stats(1, mask=5.0), stats(2, "lost"), stats(3, keyframe=True),
            stats(4, "lost", mask=1.0)]
    flags = frame_flags(rows)
    assert flags["keyframe"].tolist() == [True, False, False, True, False]
    assert flags["lost"].tolist() == [False, False, True, False, True]
    assert flags["masked"].tolist() == [False, True, False, False, True]

    class Subset:  # the poses evaluation paired with ground truth: frames 4, 1 and 3, stamps a little off
        stamps = np.array([100 + 4 / 30 + 0.004, 100 + 1 / 30 - 0.003, 100 + 3 / 30])

    paired = flags_for(Subset, rows)
    assert paired["lost"].tolist() == [True, False, False] and paired["keyframe"].tolist() == [False, False, True]
    # the camera-rate schedule names its keyframes (the jobs that made one), not the frames that asked
    assert frame_flags(rows, keyframes={1})["keyframe"].tolist() == [False, True, False, False, False]


def test_report_without_ground_truth(synthetic_sequence, tmp_path):
    copy = tmp_path / "no_gt"
    shutil.copytree(synthetic_sequence, copy)
    (copy / "groundtruth.txt").unlink()
    out = tmp_path / "run"
    result = subprocess.run([sys.executable, "-m", "twohr_app", "run", "--sequence", str(copy), "--out",
                             str(out), "--frames", "20", "--quiet", "--set", "yolo.enabled=false", "--set",
                             "detector.features=orb"], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    assert len(read_tum(out / "trajectory.txt")) == 20
    page = (out / "report.html").read_text()
    assert 'src="trajectory.png"' in page and "ATE" not in page
    assert (out / "trajectory.png").stat().st_size > 20_000
