"""The live view's TLS cost: frames per second to one viewer on ws:// and wss://, and CPU per frame at 30 Hz."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from twohr.machine import machine
from twohr.rates import ReplayPacer

#: a live-view viewer in its own process (as on another machine): subscribes to every channel and notes when each
#: image arrives; prints the count, the seconds from the first to the last, and its own CPU time
_FPS_VIEWER = """
import json, ssl, struct, sys, time
from websockets.sync.client import connect
url, cafile, frames = sys.argv[1], sys.argv[2], int(sys.argv[3])
tls = ssl.create_default_context(cafile=cafile) if url.startswith("wss:") else None
times, image = [], None
with connect(url, subprotocols=["foxglove.websocket.v1"], ssl=tls, max_size=None, compression=None) as ws:
    c0 = time.process_time()
    while len(times) < frames:
        try:
            message = ws.recv(timeout=10)
        except TimeoutError:
            break
        if isinstance(message, str):
            body = json.loads(message)
            if body["op"] == "advertise":
                ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                    {"id": c["id"], "channelId": c["id"]} for c in body["channels"]]}))
                image = next(c["id"] for c in body["channels"] if c["topic"].endswith("/camera/image"))
                print("ready", flush=True)
        elif struct.unpack_from("<I", message, 1)[0] == image:
            times.append(time.monotonic())
    cpu = time.process_time() - c0
print(json.dumps({"images": len(times), "seconds": times[-1] - times[0] if times else 0.0, "cpu_s": cpu}))
"""


def _view_run(view, url: str, cafile: Path, sequence, images: list[bytes], frames: int, rate: float,
              in_flight: int) -> dict:
    """One viewer process on ``url`` while ``frames`` frames are logged on ``view``: at ``rate`` Hz, or (0) as soon
    as fewer than ``in_flight`` messages wait in the server's queue for it. The viewer's received FPS, and CPU ms
    per frame of this process (the server) and of the viewer's."""
    import subprocess
    import sys

    view.advertise("r")
    viewer = subprocess.Popen([sys.executable, "-c", _FPS_VIEWER, url, str(cafile), str(frames)],
                              stdout=subprocess.PIPE, text=True)
    viewer.stdout.readline()  # subscribed
    time.sleep(0.3)
    pacer = ReplayPacer(fps=rate)
    c0 = time.process_time()
    for i in range(frames):
        if rate:
            pacer.wait()
        else:
            while view.backlog() >= in_flight:
                time.sleep(0.0005)
        view.log(view.converter.frame("r", float(i), sequence.camera, encoded=images[i % len(images)])
                 + view.converter.pose("r", float(i), [0.01 * i, 0, 0], [0, 0, 0, 1]))
    out, _ = viewer.communicate(timeout=300)
    server_cpu = time.process_time() - c0
    got = json.loads(out.strip().splitlines()[-1])
    return {"images": got["images"], "fps": (got["images"] - 1) / got["seconds"] if got["seconds"] else 0.0,
            "server_cpu_ms": server_cpu * 1000 / max(1, got["images"]),
            "viewer_cpu_ms": got["cpu_s"] * 1000 / max(1, got["images"])}


def view_tls_fps(sequence, frames: int = 2000, runs: int = 3, in_flight: int = 16, camera_frames: int = 300,
                 camera_rate: float = 30.0) -> dict:
    """The live view's TLS cost: frames per second one viewer (in its own process) receives, plain (``ws://``, no
    token) and on TLS with a token (``wss://``, the gateway's certificate of a fleet's keys made for the run), paired
    run by run. Each frame is one of the sequence's own JPEGs with its calibration, pose and transform (as the gateway
    shows a camera session), ``frames`` of them logged as fast as the viewer takes them (:func:`_view_run`): the
    server's throughput to one viewer. Then ``camera_frames`` at ``camera_rate`` Hz: the CPU time per frame that TLS
    adds at a camera's rate, in the server's process and in the viewer's."""
    import tempfile

    from twohr.foxglove_live import LiveView, robot_viewer, server_tls
    from twohr_app.fleet import Fleet

    images = [record.rgb_path.read_bytes() for record in sequence.records]
    camera_frames = min(camera_frames, frames)
    rows: dict[str, dict[str, list[dict]]] = {"max": {"ws": [], "wss": []}, "camera": {"ws": [], "wss": []}}
    with tempfile.TemporaryDirectory() as tmp:
        fleet = Fleet(Path(tmp) / "K")
        fleet.init()
        gateway, ca = fleet.service_folder("gateway"), fleet.folder / "ca.crt"
        for _ in range(runs):
            for mode, count, rate in (("max", frames, 0.0), ("camera", camera_frames, camera_rate)):
                for label in ("ws", "wss"):
                    tls = server_tls(gateway / "cert.pem", gateway / "key.pem") if label == "wss" else None
                    view = LiveView(port=0, tls=tls, authorize=(
                        lambda t: robot_viewer("r") if t == "bench" else None) if tls else None)
                    try:
                        url = f"{label}://127.0.0.1:{view.port}/" + ("?token=bench" if tls else "")
                        rows[mode][label].append(_view_run(view, url, ca, sequence, images, count, rate, in_flight))
                    finally:
                        view.close()

    def median(mode: str, label: str, key: str) -> float:
        return round(float(np.median([row[key] for row in rows[mode][label]])), 2)

    fps = {label: median("max", label, "fps") for label in ("ws", "wss")}
    return {"sequence": sequence.name, "frames": frames, "runs": runs, "in_flight": in_flight,
            "image_kb_mean": round(sum(len(i) for i in images) / len(images) / 1000, 1),
            "received": {label: [row["images"] for row in rows["max"][label]] for label in ("ws", "wss")},
            "fps": {label: [round(row["fps"], 1) for row in rows["max"][label]] for label in ("ws", "wss")},
            "fps_median": fps,
            "tls_fps_change_percent": round(100 * (fps["wss"] - fps["ws"]) / fps["ws"], 1) if fps["ws"] else None,
            "camera_rate": {"hz": camera_rate, "frames": camera_frames, **{
                f"{side}_cpu_ms_per_frame": {label: median("camera", label, f"{side}_cpu_ms")
                                             for label in ("ws", "wss")} for side in ("server", "viewer")},
                "fps_median": {label: median("camera", label, "fps") for label in ("ws", "wss")}},
            "machine": machine()}
