"""The Foxglove live view's CPU cost in ``twohr run --view``, one viewer subscribed from another process."""

from __future__ import annotations

import json
import os
import platform
import time

import numpy as np

from twohr.config import PipelineConfig
from twohr_app.pipeline import run_sequence

#: a Foxglove viewer in its own process (as on another machine): subscribes to every channel, counts the messages
_VIEWER = """
import json, sys, time
from twohr.foxglove_live import FoxgloveClient
client = FoxgloveClient(sys.argv[1])
deadline = time.monotonic() + 30
while len(client.subscriptions) < int(sys.argv[2]) and time.monotonic() < deadline:
    time.sleep(0.05)
print("ready", flush=True)
sys.stdin.read()
time.sleep(0.5)
print(json.dumps(client.counts), flush=True)
client.close()
"""


def view_cost(sequence, config: PipelineConfig, frames: int = 60, start: int = 0, runs: int = 3,
              progress: bool = True) -> dict:
    """CPU time per frame of the pipeline streaming to the Foxglove live view (``twohr run --view``, with one
    viewer subscribed to every channel from another process) against the same run without it, paired run by
    run. CPU time is this process's, all threads (the live view server's included), from the first frame's end
    to the last's."""
    import subprocess
    import sys

    from twohr.foxglove_convert import topics
    from twohr_app.live_view import PipelineLiveView

    stop = min(len(sequence), start + frames)
    cpu_ms: dict[str, list[float]] = {"without_view": [], "with_view": []}
    fps: dict[str, list[float]] = {"without_view": [], "with_view": []}
    received: list[dict] = []
    for _ in range(runs):
        for label in ("without_view", "with_view"):
            view = viewer = None
            if label == "with_view":
                view = PipelineLiveView(sequence, port=0)
                viewer = subprocess.Popen([sys.executable, "-c", _VIEWER, f"ws://127.0.0.1:{view.view.port}",
                                           str(len(topics("run")))], stdin=subprocess.PIPE,
                                          stdout=subprocess.PIPE, text=True)
                viewer.stdout.readline()  # subscribed
            cpu: list[float] = []

            def on_frame(*args, view=view, cpu=cpu):
                if view is not None:
                    view(*args)
                cpu.append(time.process_time())  # after each frame: model loading and the first frame left out

            try:
                run = run_sequence(sequence, config, start=start, stop=stop, progress=progress, on_frame=on_frame)
                cpu_ms[label].append((cpu[-1] - cpu[0]) * 1000 / max(1, len(cpu) - 1))
                fps[label].append(len(run.stats) / run.wall_s)
            finally:
                if viewer is not None:
                    out, _ = viewer.communicate("", timeout=60)
                    received.append(json.loads(out.strip().splitlines()[-1]))
                if view is not None:
                    view.close()
    base, viewed = float(np.median(cpu_ms["without_view"])), float(np.median(cpu_ms["with_view"]))
    return {"sequence": sequence.name, "frames": stop - start, "runs": runs, "mode": config.pipeline.mode,
            "cpu_ms_per_frame": {k: [round(v, 2) for v in vals] for k, vals in cpu_ms.items()},
            "cpu_ms_per_frame_median": {"without_view": round(base, 2), "with_view": round(viewed, 2)},
            "view_cpu_ms_per_frame": round(viewed - base, 2),
            "view_cpu_percent": round(100 * (viewed - base) / base, 1) if base else None,
            "fps_median": {k: round(float(np.median(v)), 2) for k, v in fps.items()},
            "viewer_received_per_run": received,
            "machine": {"cpus": os.cpu_count(), "platform": platform.platform()}}
