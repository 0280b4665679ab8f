"""Maps that outlive a run: the map file (round trip, atomic write, every kind of bad file as one line), a tracker
that finds itself in a loaded map with no prior pose, and ``twohr run --save-map`` / ``--map`` on real frames."""

from __future__ import annotations

import json
import subprocess
import sys
import zipfile

import numpy as np
import pytest

from twohr.config import DetectorConfig, load_config
from twohr.dataset import RGBDSequence
from twohr.evaluation import evaluate
from twohr.mapfile import MapFileError, read_header, read_map, verify_bytes
from twohr.models import get_spec
from twohr.pose import pose_difference
from twohr.trajectory import Trajectory, read_tum
from twohr_services.tracker.mapfiles import load_map, save_map
from twohr_services.tracker.tracking import Tracker

from .test_tracking import SYNTHETIC, feed, truth_in_first_camera

ORB = load_config(None, {"detector.features": "orb", "yolo.enabled": False, "matcher.method": "mutual_nn"})
ORB = ORB.model_copy(update={"tracker": SYNTHETIC})


def _built(data, frames=range(30)) -> Tracker:
    tracker = Tracker(data.camera, SYNTHETIC, match=data.match)
    results = feed(tracker, data, frames)
    assert all(r.tracked for r in results)
    return tracker


def test_a_map_file_holds_the_map_as_it_was(orb_synthetic, tmp_path):
    world = _built(orb_synthetic).map
    header, size, _ = save_map(tmp_path / "room.map", world, ORB, built_by="test")
    assert header.name == "room" and header.keyframes == len(world.keyframes) >= 3
    assert size == (tmp_path / "room.map").stat().st_size and not list(tmp_path.glob(".*.tmp"))
    assert read_header(tmp_path / "room.map").landmarks == len(world.landmarks)
    loaded, again, _ = load_map(tmp_path / "room.map", ORB, orb_synthetic.camera)
    assert again == header
    assert np.array_equal(loaded.keyframe_poses, world.keyframe_poses)
    assert np.array_equal(loaded.landmarks.positions, world.landmarks.positions)
    assert np.array_equal(loaded.landmarks.descriptors, world.landmarks.descriptors)
    assert np.array_equal(loaded.landmarks.bad, world.landmarks.bad)
    for a, b in zip(loaded.keyframes, world.keyframes, strict=True):
        assert np.array_equal(a.landmark_ids, b.landmark_ids) and np.allclose(a.xy, b.xy, atol=1e-4)


def test_a_bad_map_file_is_one_line(orb_synthetic, tmp_path):
    world = _built(orb_synthetic).map
    good = tmp_path / "room.map"
    save_map(good, world, ORB)
    (tmp_path / "text.map").write_text("not a map")
    truncated = tmp_path / "truncated.map"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    inconsistent = tmp_path / "inconsistent.map"
    with zipfile.ZipFile(good) as source, zipfile.ZipFile(inconsistent, "w") as target:
        for item in source.namelist():
            data = source.read(item)
            if item == "header.json":
                header = json.loads(data)
                header["landmarks"] += 1
                data = json.dumps(header).encode()
            target.writestr(item, data)
    newer = tmp_path / "newer.map"
    with zipfile.ZipFile(good) as source, zipfile.ZipFile(newer, "w") as target:
        for item in source.namelist():
            data = source.read(item)
            target.writestr(item, json.dumps({**json.loads(data), "version": 99}) if item == "header.json" else data)
    cases = {tmp_path / "missing.map": "no such map file", tmp_path / "text.map": "not a twohr map file",
             truncated: "not a twohr map file", inconsistent: "the header says", newer: "version 99"}
    for path, says in cases.items():
        with pytest.raises(MapFileError, match=says) as caught:
            read_map(path)
        assert "\n" not in str(caught.value)
    with pytest.raises(MapFileError, match="descriptors would not match"):
        read_map(good, detector=ORB.detector.model_copy(update={"model": "another_model"}))
    with pytest.raises(MapFileError, match="orb features"):  # ORB descriptors against 2HR ones: same model name
        read_map(good, detector=DetectorConfig())
    other_camera = orb_synthetic.camera.model_copy(update={"fx": orb_synthetic.camera.fx * 1.1})
    with pytest.raises(MapFileError, match="another camera"):
        load_map(good, ORB, other_camera)
    assert verify_bytes(good.read_bytes()).name == "room"
    with pytest.raises(MapFileError):
        verify_bytes(b"PK\x03\x04 not really")


def test_a_map_is_read_by_every_network_of_its_descriptor_space(orb_synthetic, tmp_path):
    """faster2d2, its INT8 build and auto (whose candidates are those two) give descriptors of one space: a map
    built by any of them is read by the others, with faster2d2's checksum in its header. R2D2 and the student give
    other descriptors: their runs are refused."""
    world = _built(orb_synthetic).map
    faster2d2_sha = get_spec("faster2d2_WASF_N16").sha256
    one_space = ("faster2d2", "faster2d2_WASF_N16", "faster2d2-int8", "auto")
    for built_with in ("faster2d2", "faster2d2-int8", "auto"):
        path = tmp_path / f"{built_with}.map"
        header, _, _ = save_map(path, world, ORB.model_copy(update={"detector": _detector(built_with)}))
        assert (header.detector_model, header.detector_sha256) == (built_with, faster2d2_sha)
        for reader in one_space:
            assert read_map(path, detector=_detector(reader)).header.keyframes == len(world.keyframes)
        for reader in ("r2d2", "student"):
            with pytest.raises(MapFileError, match=f"built with detector '{built_with}'"):
                read_map(path, detector=_detector(reader))


def _detector(model: str) -> DetectorConfig:
    return ORB.detector.model_copy(update={"model": model})


def test_a_tracker_finds_itself_in_a_loaded_map_with_no_prior_pose(orb_synthetic, tmp_path):
    """Built on frames 0-29, saved, loaded by a new tracker that starts at frame 40: no pose until it is found in
    the map, then poses in the map's frame (the first run's first camera), as accurate as the first run's."""
    save_map(tmp_path / "room.map", _built(orb_synthetic).map, ORB)
    loaded, _, _ = load_map(tmp_path / "room.map", ORB, orb_synthetic.camera)
    tracker = Tracker(orb_synthetic.camera, SYNTHETIC, match=orb_synthetic.match, world=loaded)
    assert tracker.relocalising and not tracker.localised
    frames = list(range(40, 60))
    results = feed(tracker, orb_synthetic, frames)
    assert results[0].status == "relocalised" and "whole map" in results[0].reason
    for index, result in zip(frames, results, strict=True):
        moved, turned = pose_difference(truth_in_first_camera(orb_synthetic, index), result.pose)
        assert result.tracked and moved < 0.01 and turned < 0.5, (index, moved, turned)


def test_a_tracker_in_a_loaded_map_has_no_pose_where_the_map_is_not(orb_synthetic, orb_synthetic_other_room,
                                                                   tmp_path):
    """Frames of another room: the tracker keeps looking (``relocalising``, no pose), never starts a map of its
    own in the loaded map's frame; back in the mapped room, it is found."""
    save_map(tmp_path / "room.map", _built(orb_synthetic).map, ORB)
    loaded, _, _ = load_map(tmp_path / "room.map", ORB, orb_synthetic.camera)
    tracker = Tracker(orb_synthetic.camera, SYNTHETIC, match=orb_synthetic.match, world=loaded)
    elsewhere = [tracker.track(1000 + n / 30, orb_synthetic_other_room.keypoints[n], orb_synthetic_other_room.depths[n])
                 for n in range(20)]
    assert all(r.status == "relocalising" and not r.posed for r in elsewhere)
    assert len(tracker.map.keyframes) == len(loaded.keyframes)
    back = tracker.track(1001, orb_synthetic.keypoints[10], orb_synthetic.depths[10])
    moved, _ = pose_difference(truth_in_first_camera(orb_synthetic, 10), back.pose)
    assert back.status == "relocalised" and moved < 0.01


def _twohr(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "twohr_app", *args], capture_output=True, text=True,
                          timeout=600)


def test_twohr_run_saves_a_map_and_a_second_run_localizes_in_it(dev_sequence, tmp_path):
    """The issue's check, on a short stretch: build on frames 0-59 and save; a second run from frame 60 loads the
    map, finds itself in it and tracks in its frame: both trajectories together fit the ground truth with one
    alignment. A map that is not one is refused in one line with exit 2."""
    fast = ["--set", "detector.input_scale=0.5", "--quiet"]
    built = _twohr("run", "--sequence", str(dev_sequence), "--frames", "60", "--save-map", str(tmp_path / "lab.map"),
                   "--out", str(tmp_path / "A"), *fast)
    assert built.returncode == 0, built.stderr
    saved = json.loads((tmp_path / "A" / "summary.json").read_text())["saved_map"]
    assert saved["name"] == "lab" and saved["keyframes"] >= 2 and saved["size_bytes"] > 0
    localized = _twohr("run", "--sequence", str(dev_sequence), "--start", "60", "--frames", "40", "--map",
                       str(tmp_path / "lab.map"), "--map-mode", "localize", "--out", str(tmp_path / "B"), *fast)
    assert localized.returncode == 0, localized.stderr
    found = json.loads((tmp_path / "B" / "summary.json").read_text())["map"]
    assert found["posed_percent"] >= 90 and found["relocalised_after_frames"] <= 3, found
    a, b = read_tum(tmp_path / "A" / "trajectory.txt"), read_tum(tmp_path / "B" / "trajectory.txt")
    joined = Trajectory(np.concatenate([a.stamps, b.stamps]), np.concatenate([a.poses, b.poses]))
    sequence = RGBDSequence(dev_sequence)
    extrinsic = sequence.default_gt_extrinsic()
    report, _ = evaluate(sequence.ground_truth(extrinsic), joined, gt_extrinsic=extrinsic)
    assert report.matched >= 95 and report.ate.rmse < 0.03, report.ate.rmse  # one SE(3) alignment for both runs
    (tmp_path / "broken.map").write_bytes(b"garbage")
    refused = _twohr("run", "--sequence", str(dev_sequence), "--start", "60", "--frames", "5", "--map",
                     str(tmp_path / "broken.map"), "--out", str(tmp_path / "C"), *fast)
    assert refused.returncode == 2 and "not a twohr map file" in refused.stderr
    assert "Traceback" not in refused.stderr and len(refused.stderr.strip().splitlines()) == 1
    in_place = _twohr("run", "--sequence", str(dev_sequence), "--frames", "5", "--map", str(tmp_path / "lab.map"),
                      "--map-mode", "extend", "--save-map", str(tmp_path / "lab.map"), "--out", str(tmp_path / "D"),
                      *fast)
    assert in_place.returncode == 2 and "never overwritten in place" in in_place.stderr
