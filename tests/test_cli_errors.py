"""Bad input on the command line (``twohr run``, ``twohr eval``): one clear line and exit code 2, or a corrupt
frame skipped with a one-line warning. Small bad sequences are cut from the real dev frames."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from twohr.dataset import RGBDSequence

FRAMES = 12
TRUNCATED = 6


def twohr(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "twohr_app", *args], capture_output=True, text=True,
                          timeout=600)


def one_error_line(result: subprocess.CompletedProcess) -> str:
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and lines[0].startswith("twohr: error: "), result.stderr
    assert "Traceback" not in result.stderr and "Warning" not in result.stderr
    return lines[0]


@pytest.fixture(scope="module")
def short_sequence(dev_sequence, tmp_path_factory) -> Path:
    """The first dev frames, with their associations and ground truth."""
    root = tmp_path_factory.mktemp("seq") / "rgbd_bonn_short"
    lines = (dev_sequence / "associations.txt").read_text().splitlines()[:FRAMES]
    for line in lines:
        for name in line.split()[1::2]:
            (root / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(dev_sequence / name, root / name)
    (root / "associations.txt").write_text("\n".join(lines) + "\n")
    shutil.copyfile(dev_sequence / "groundtruth.txt", root / "groundtruth.txt")
    return root


def test_a_truncated_jpeg_is_skipped_with_one_warning(short_sequence, tmp_path):
    bad = tmp_path / "rgbd_bonn_truncated"
    shutil.copytree(short_sequence, bad)
    jpeg = RGBDSequence(bad).records[TRUNCATED].rgb_path
    jpeg.write_bytes(jpeg.read_bytes()[: jpeg.stat().st_size // 2])
    out = tmp_path / "run"
    result = twohr("run", "--sequence", str(bad), "--out", str(out), "--quiet", "--set", "detector.input_scale=0.5",
                   "--set", "pipeline.synchronous=true")
    assert result.returncode == 0, result.stderr
    warnings = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(warnings) == 1 and f"skipping frame {TRUNCATED}" in warnings[0] and jpeg.name in warnings[0], warnings
    summary = json.loads((out / "summary.json").read_text())
    assert summary["skipped_frames"] == [TRUNCATED] and summary["frames"] == FRAMES - 1
    stats = (out / "stats.csv").read_text().splitlines()[1:]
    assert sorted(int(row.split(",")[0]) for row in stats) == [i for i in range(FRAMES) if i != TRUNCATED]
    assert summary["tracked_percent"] == 100.0


@pytest.mark.parametrize(("flags", "says"), [
    (["--start", str(FRAMES)], f"start frame {FRAMES} is out of range"),
    (["--start", "-1"], "start frame -1 is out of range"),
    (["--frames", "0"], "frames must be at least 1"),
    (["--frames", "-5"], "frames must be at least 1"),
    (["--step", "0"], "step must be at least 1"),
])
def test_an_empty_frame_range_is_one_line_and_exit_2(short_sequence, tmp_path, flags, says):
    out = tmp_path / "run"
    result = twohr("run", "--sequence", str(short_sequence), "--out", str(out), "--quiet", *flags)
    assert says in one_error_line(result)
    assert not out.exists(), "no outputs for a run that never started"


def test_zero_quaternions_in_eval_are_one_line_and_exit_2(short_sequence, tmp_path):
    est = tmp_path / "est.txt"
    rows = (short_sequence / "groundtruth.txt").read_text().splitlines()
    data = [r for r in rows if r and not r.startswith("#")][:20]
    fields = data[7].split()
    data[7] = " ".join(fields[:4] + ["0", "0", "0", "0"])
    est.write_text("\n".join(data) + "\n")
    result = twohr("eval", "--gt", str(short_sequence / "groundtruth.txt"), "--est", str(est))
    line = one_error_line(result)
    assert f"{est}:8:" in line and "quaternion" in line and "nan" not in result.stdout.lower()
    data[7] = " ".join(fields[:4] + ["nan", "0", "0", "1"])
    est.write_text("\n".join(data) + "\n")
    assert "not a finite number" in one_error_line(twohr("eval", "--gt", str(short_sequence / "groundtruth.txt"),
                                                         "--est", str(est)))


def test_zero_quaternions_in_a_recording_are_one_line_and_exit_2(short_sequence, tmp_path):
    from twohr.messages import PoseMsg, encode
    from twohr.trajectory import read_tum
    from twohr_services.recorder.core import SessionRecorder

    gt = read_tum(short_sequence / "groundtruth.txt")
    recorder = SessionRecorder(tmp_path / "est.mcap")
    for i in range(20):
        orientation = [0.0, 0.0, 0.0, 0.0] if i == 7 else [0.0, 0.0, 0.0, 1.0]
        recorder.write("twohr/r1/pose", encode(PoseMsg(session_id="s", robot_id="r1", frame_index=i,
                                                       stamp=gt.stamps[i], position=gt.positions[i].tolist(),
                                                       orientation=orientation, status="tracking")))
    recorder.close()
    line = one_error_line(twohr("eval", "--gt", str(short_sequence / "groundtruth.txt"), "--est",
                                str(tmp_path / "est.mcap")))
    assert "frames [7]" in line and "orientation" in line


def test_map_versions_are_checked_in_one_place_and_a_rollback_is_audited_beside_the_maps(tmp_path, tiny_map):
    """``--map-versions`` is one line wherever it is given, and ``twohr maps rollback`` appends to the map store's
    audit trail (``MAPS/audit.jsonl``, the file ``twohr up --maps MAPS`` has the gateway write), not to a file
    relative to wherever it was run."""
    from twohr.dataset import CameraIntrinsics
    from twohr.mapfile import encode_map
    from twohr.mapstore import MapStore

    maps = tmp_path / "maps"
    store = MapStore(maps)
    camera = CameraIntrinsics(fx=500, fy=500, cx=319.5, cy=239.5, width=640, height=480)
    for shift in range(2):
        made = tiny_map("lab", camera)
        made.arrays.landmark_positions += shift
        store.save(encode_map(made), builder="a")
    for command, value in ((["up"], "0"), (["up"], "10001"), (["up"], "abc"),
                           (["maps", "rollback", "lab", "--version", "1", "--maps", str(maps)], "0"),
                           (["maps", "rollback", "lab", "--version", "1", "--maps", str(maps)], "1.5")):
        line = one_error_line(twohr(*command, "--map-versions", value))
        assert f"--map-versions {value}: keep at least one version of each map and at most 10000" in line, line
    assert store.numbers("lab") == [1, 2]
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    done = subprocess.run([sys.executable, "-m", "twohr_app", "maps", "rollback", "lab", "--version", "1", "--maps",
                           str(maps)], capture_output=True, text=True, timeout=600, cwd=elsewhere)
    assert done.returncode == 0 and f"logged in {maps / 'audit.jsonl'}" in done.stdout, done.stdout + done.stderr
    logged = [json.loads(line) for line in (maps / "audit.jsonl").read_text().splitlines()]
    assert [(e["action"], e["map"], e["version"]) for e in logged] == [("map.rollback", "lab", 3)]
    assert list(elsewhere.iterdir()) == []


def test_twohr_up_stops_at_once_with_the_line_of_a_child_that_cannot_start(tmp_path):
    """A child that exits while the stack starts (the gateway refuses a short API token) ends ``twohr up`` at once,
    with that child's last line, not after ``--timeout`` with "the gateway did not answer"."""
    from twohr.bus import free_port

    started = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "twohr_app", "up", "--api-token", "short", "--timeout", "300",
                           "--router", f"tcp/127.0.0.1:{free_port()}", "--port", str(free_port()),
                           "--foxglove-port", "0", "--max-robots", "1", "--data-root", str(tmp_path),
                           "--recordings", str(tmp_path / "recordings"),
                           "--write-client-config", str(tmp_path / "client.json5")],
                          capture_output=True, text=True, timeout=240, cwd=tmp_path)
    took = time.monotonic() - started
    last = done.stderr.strip().splitlines()[-1]
    assert done.returncode == 2 and last.startswith("twohr: error: gateway exited with code 2 during start-up: "
                                                    "gateway: error: "), done.stderr
    assert "the API token must have at least 16 characters" in last and "did not answer" not in done.stderr
    assert took < 60, f"twohr up took {took:.0f} s to give up"  # the stack's start, not --timeout's 300 s
    assert done.stderr.count("the API token must have at least 16 characters") == 2  # the gateway's, and ours
