"""Seeing it live, on the whole system as `twohr up` starts it: the session page in headless Chromium, the
Foxglove live view on --foxglove-port, and the lean recording.

`twohr up --router tcp/127.0.0.1:P --port H --data-root D --foxglove-port F`, then a 120-frame session on the
dev sequence: the page shows it and its live frame count, a Foxglove WebSocket client is advertised the
image, pose, map points and calibration channels and receives messages on them, and the recording is at
most 100 kB per frame and read by standard MCAP readers. Screenshots go to the test's tmp folder.
"""

import os
import re
import subprocess
import sys
import time

import httpx
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from playwright.sync_api import expect, sync_playwright

from conftest import read_until
from twohr.bus import free_port
from twohr_services.recorder.core import recorded_trajectory

CHROMIUM = "/usr/bin/chromium"
FRAMES = 120


@pytest.fixture(scope="module")
def stack(dev_sequence, tmp_path_factory):
    """`twohr up` as a user starts it, on free ports."""
    recordings = tmp_path_factory.mktemp("view_recordings")
    router, port, fox = f"tcp/127.0.0.1:{free_port()}", free_port(), free_port()
    proc = subprocess.Popen([sys.executable, "-m", "twohr_app", "up", "--router", router, "--port", str(port),
                             "--data-root", str(dev_sequence.parent), "--foxglove-port", str(fox), "--recordings",
                             str(recordings)], stdout=subprocess.PIPE, text=True)
    lines = read_until(proc, "live view:")
    if not lines[-1:] or not lines[-1].startswith("live view:"):
        pytest.fail("twohr up did not come up:\n" + "".join(lines))
    assert f"ds.url=ws://127.0.0.1:{fox}" in lines[-1]
    yield {"url": f"http://127.0.0.1:{port}", "foxglove": f"ws://127.0.0.1:{fox}", "fox_port": fox}
    proc.send_signal(2)  # Ctrl-C
    try:
        proc.wait(60)
    except subprocess.TimeoutExpired:
        proc.kill()


@pytest.fixture(scope="module")
def browser():
    if not os.path.exists(CHROMIUM):
        pytest.fail(f"Debian's chromium is required at {CHROMIUM} (apt-get install chromium; .ci/run installs it)")
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, headless=True)
        yield browser
        browser.close()


def frames_shown(row) -> int:
    return int(row.locator("td.frames").inner_text().split("/")[0])


def test_live_session_on_page_foxglove_and_lean_recording(stack, dev_sequence, browser, foxglove_listener, tmp_path):
    page = browser.new_page(viewport={"width": 1400, "height": 600})
    with httpx.Client(base_url=stack["url"], timeout=30) as client:
        index = client.get("/")
        assert index.status_code == 200 and index.headers["content-type"].startswith("text/html")
        page.goto(stack["url"] + "/")
        link = page.locator("#foxglove-link")
        expect(link).to_be_visible()
        assert link.get_attribute("href").endswith(f"ds=foxglove-websocket&ds.url=ws://127.0.0.1:{stack['fox_port']}")

        fox = foxglove_listener(stack["foxglove"])
        response = client.post("/sessions", json={"sequence": dev_sequence.name, "robot_id": "robot_v",
                                                  "max_frames": FRAMES})
        assert response.status_code == 201, response.text
        session_id = response.json()["id"]

        row = page.locator(f"tr[data-session='{session_id}']")
        expect(row).to_be_visible(timeout=30_000)
        expect(row.locator("td.sequence")).to_have_text(dev_sequence.name)
        seen = []
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            seen.append(frames_shown(row))
            state = row.locator("td.state").inner_text()
            if 20 <= seen[-1] < FRAMES and len(seen) > 1 and not (tmp_path / "running.png").exists():
                page.screenshot(path=tmp_path / "running.png", full_page=True)  # the page during the session
            if state == "finished":
                break
            time.sleep(0.3)
        assert state == "finished", (state, seen)
        expect(row.locator("td.frames")).to_have_text(f"{FRAMES} / {FRAMES}")
        assert len(set(seen)) >= 3 and seen == sorted(seen), seen  # the page showed the count rising
        assert (tmp_path / "running.png").stat().st_size > 10_000
        expect(row.locator("td.tracking")).to_have_text(re.compile("tracking|relocalised"))
        page.screenshot(path=tmp_path / "finished.png", full_page=True)

        recording = client.get(f"/sessions/{session_id}/recording")
        assert recording.status_code == 200

    # the live view: every channel advertised, messages received on each
    topics = fox.topics()
    for topic, schema in {"/robot_v/camera/image": "foxglove.CompressedImage", "/robot_v/pose": "foxglove.PoseInFrame",
                          "/robot_v/map": "foxglove.PointCloud", "/tf": "foxglove.FrameTransforms",
                          "/robot_v/camera/calibration": "foxglove.CameraCalibration",
                          "/robot_v/path": "foxglove.PosesInFrame"}.items():
        assert topics.get(topic) == schema, topics
    counts = fox.counts
    # the first frame of each channel advertises it and may pass before the client subscribes
    assert counts["/robot_v/camera/image"] >= FRAMES - 3 and counts["/robot_v/camera/calibration"] >= FRAMES - 3
    assert counts["/robot_v/pose"] >= FRAMES - 3 and counts["/tf"] >= FRAMES - 3, counts
    assert counts["/robot_v/map"] >= 2 and counts["/robot_v/camera/keypoints"] >= 2, counts
    cloud = fox.decode("/robot_v/map")
    assert len(cloud.data) // cloud.point_stride > 100

    # the recording: lean, and standard readers read it
    path = tmp_path / "session.mcap"
    path.write_bytes(recording.content)
    per_frame = path.stat().st_size / FRAMES
    print(f"recording: {path.stat().st_size} bytes, {per_frame / 1000:.1f} kB per frame")
    assert per_frame <= 100_000, per_frame
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
        counts = {c.topic: summary.statistics.channel_message_counts[i] for i, c in summary.channels.items()}
        assert counts["/robot_v/camera/image"] == FRAMES and counts["/twohr/robot_v/pose"] == FRAMES, counts
        assert counts["/robot_v/map"] >= 2 and counts["/robot_v/camera/calibration"] == FRAMES, counts
        fh.seek(0)
        decoded = 0
        for _s, _c, _m, proto in make_reader(fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                topics=["/robot_v/camera/image", "/robot_v/pose", "/robot_v/map", "/robot_v/path"]):
            decoded += 1
            assert proto.timestamp.seconds > 1e9
        assert decoded == 2 * FRAMES + counts["/robot_v/map"] + counts["/robot_v/path"]
    assert len(recorded_trajectory(path)) == FRAMES


def test_page_starts_stops_and_downloads(stack, dev_sequence, browser, tmp_path):
    page = browser.new_page(viewport={"width": 1400, "height": 600}, accept_downloads=True)
    page.goto(stack["url"] + "/")
    page.fill("#sequence", dev_sequence.name)
    page.fill("#robot", "robot_page")
    page.fill("#rate", "1")  # the camera's rate: slow enough to stop half-way
    page.click("#start")
    expect(page.locator("#message")).to_contain_text("started session")
    session_id = page.locator("#message").inner_text().split()[-1]
    row = page.locator(f"tr[data-session='{session_id}']")
    expect(row.locator("td.state")).to_have_text("running", timeout=60_000)
    first = frames_shown(row)
    deadline = time.monotonic() + 120
    while frames_shown(row) < first + 10:
        assert time.monotonic() < deadline, "the pose count did not rise"
        time.sleep(0.3)
    page.screenshot(path=tmp_path / "page_running.png", full_page=True)
    row.locator("button.stop").click()
    expect(row.locator("td.state")).to_have_text("stopped")
    expect(row.locator("button.stop")).to_be_hidden()
    shown = frames_shown(row)
    with page.expect_download() as info:
        row.locator("button.download-trajectory").click()
    saved = tmp_path / info.value.suggested_filename
    info.value.save_as(saved)
    assert saved.name == f"{session_id}_trajectory.txt"
    poses = [line for line in saved.read_text().splitlines() if line and not line.startswith("#")]
    assert len(poses) >= shown >= first + 10
    assert all(len(line.split()) == 8 for line in poses)
    # a request the API refuses is shown on the page, in one line
    page.fill("#sequence", "no_such_sequence")
    page.click("#start")
    expect(page.locator("#message")).to_contain_text("could not start: 422")
