"""``twohr yolo``: eval, viz and detect on real frames, and one-line errors."""

from __future__ import annotations

import json

import cv2

from twohr_app.cli import main


def test_eval_writes_per_frame_stats(dev_sequence, tmp_path, capsys):
    out = tmp_path / "eval"
    assert main(["yolo", "eval", "--sequence", str(dev_sequence), "--start", "440", "--frames", "2", "--step", "5",
                 "--keypoints", "orb", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 2 and summary["detector_runs"] == 2
    assert summary["detections_per_frame"]["high"] >= 2 and summary["frames_with_person_pct"] == 100.0
    # people fill these frames: boxes cover most of the image, the depth mask less
    assert summary["box"]["mask_area_pct_mean"] > 60
    assert summary["depth"]["mask_area_pct_mean"] < summary["box"]["mask_area_pct_mean"]
    assert 30 < summary["box"]["keypoints_removed_pct_pooled"] <= 100
    rows = (out / "frames.csv").read_text().splitlines()
    assert len(rows) == 3 and rows[0].startswith("index,stamp,fresh,det_high")
    assert (out / "eval.png").stat().st_size > 10_000


def test_viz_and_detect(dev_sequence, tmp_path, capsys):
    out = tmp_path / "viz"
    assert main(["yolo", "viz", "--sequence", str(dev_sequence), "--indices", "300", "--keypoints", "none",
                 "--out", str(out)]) == 0
    picture = cv2.imread(str(out / "frame_0300.png"))
    assert picture.shape == (480 + 24, 2 * 640, 3)
    image = sorted((dev_sequence / "rgb").iterdir())[300]
    capsys.readouterr()
    assert main(["yolo", "detect", str(image)]) == 0
    printed = capsys.readouterr().out
    assert printed.count("person") >= 2 and "high" in printed


def test_user_errors_are_one_line(dev_sequence, tmp_path, capsys):
    corrupt = tmp_path / "corrupt.jpg"
    corrupt.write_bytes(b"not a jpeg")
    for argv, message in [
        (["yolo", "detect", str(corrupt)], "not a readable image"),
        (["yolo", "detect", str(tmp_path / "absent.png")], "image not found"),
        (["yolo", "eval", "--sequence", str(tmp_path / "nowhere")], "sequence folder not found"),
        (["yolo", "eval", "--model", "yolov99", "--sequence", str(dev_sequence)], "unknown model"),
        (["yolo", "eval", "--model", "r2d2_WASF_N16", "--sequence", str(dev_sequence)], "not a YOLO detector"),
        (["yolo", "viz", "--table", str(tmp_path / "absent.yaml")], "dynamics table not found"),
    ]:
        capsys.readouterr()
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and "\n" not in err and "Traceback" not in err
