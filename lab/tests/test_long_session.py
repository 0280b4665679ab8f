"""The long-session study on a small synthetic room swept back and forth: checkpoints every 60 frames, one row per
configuration and checkpoint, and with landmark rows reused fewer rows than landmarks made."""

from __future__ import annotations

import csv

import pytest

from twohr.synthetic import SyntheticSpec
from twohr_lab.tracking import long_session

FAST = ("detector.features=orb,yolo.enabled=false,matcher.method=mutual_nn,tracker.depth_noise=0.005,"
        "pipeline.synchronous=true,tracker.refine_frames=30")  # a short refinement window frees rows sooner


def test_checkpoints_of_each_configuration_with_rows_and_memory(synthetic_room, tmp_path):
    # the room of test_keyframe_policy.py's sweeps: rendered once per session
    sequence = synthetic_room(SyntheticSpec(frames=360, occluders=0, seed=3, motion="pan", pan_deg=60, sweeps=12))
    out = tmp_path / "out"
    assert long_session.main(["--sequence", str(sequence), "--every", "60", "--out", str(out),
                              "--config", f"reuse={FAST}",
                              "--config", f"every-row={FAST},tracker.reuse_landmark_rows=false"]) == 0
    rows = list(csv.DictReader(open(out / "rows.tsv"), delimiter="\t"))
    assert [(r["config"], int(r["frames"])) for r in rows] == [
        (name, frames) for name in ("reuse", "every-row") for frames in range(60, 361, 60)]
    last = {r["config"]: r for r in rows if r["frames"] == "360"}
    assert int(last["every-row"]["landmark_rows"]) == int(last["every-row"]["landmarks"])
    assert int(last["reuse"]["landmark_rows"]) < int(last["reuse"]["landmarks"]), last["reuse"]
    assert all(float(r["rss_mib"]) > 50 for r in rows)
    text = (out / "long_session.md").read_text()
    assert "`reuse`" in text and "refined ATE" in text and (out / "long_session.png").stat().st_size > 10_000


def test_it_refuses_a_sequence_without_ground_truth(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        long_session.main(["--sequence", str(tmp_path), "--out", str(tmp_path / "out")])
    assert exit_info.value.code == 2 and "no groundtruth.txt" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
