"""``twohr bench``: throughput, per-stage latency and memory of the pipeline, and the ablation table.

A lab study over :mod:`twohr_app.pipeline` (``run_sequence``, the front end). Timings are medians
over several runs, each against a baseline measured in the same process at the same time (this machine is shared).
"""

from __future__ import annotations

import json
import os
import platform
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twohr.config import PRESETS, PipelineConfig, load_config, merge_overrides
from twohr.evaluation import evaluate
from twohr.machine import machine
from twohr.models import REPO_ROOT
from twohr.trajectory import Trajectory
from twohr_app.pipeline import FrontEnd, StageOutput, run_sequence

#: The ablation variants: the table's row -> config overrides on top of the user's config. They are the product's
#: named presets (``twohr run --preset NAME`` runs one row alone).
ABLATIONS: dict[str, dict[str, object]] = {preset.label: preset.overrides for preset in PRESETS.values()}


def peak_rss_mib() -> float:
    """Peak resident memory of this process so far, MiB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _percentiles(values: list[float]) -> dict[str, float]:
    arr = np.asarray(values, float)
    return {"median": round(float(np.median(arr)), 2), "p90": round(float(np.percentile(arr, 90)), 2),
            "p99": round(float(np.percentile(arr, 99)), 2)}


#: Where ORB-SLAM3's vocabulary and settings for the dev camera live (``../shared/baselines`` beside the repo);
#: override with $PYORBSLAM3_VOCAB and $TWOHR_ORBSLAM3_SETTINGS.
BASELINES_DIR = REPO_ROOT.parent / "shared" / "baselines"


def orbslam3_files() -> tuple[Path, Path] | None:
    """(vocabulary, settings) for ORB-SLAM3 RGB-D, or None when pyorbslam3 or the files are missing."""
    try:
        import pyorbslam3  # noqa: F401  (GPL-3.0, an optional benchmark comparison, not a dependency)
    except ImportError:
        return None
    vocab = Path(os.environ.get("PYORBSLAM3_VOCAB", BASELINES_DIR / "ORBvoc_generic_nobonn_k10L6.txt"))
    settings = Path(os.environ.get("TWOHR_ORBSLAM3_SETTINGS", BASELINES_DIR / "orbslam3_bonn_rgbd.yaml"))
    return (vocab, settings) if vocab.is_file() and settings.is_file() else None


def memory_available_mib() -> float | None:
    """Memory available to a new allocation without swapping (Linux ``MemAvailable``), MiB; None elsewhere."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) / 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def frames_fit_in_memory(sequence, start: int, stop: int, share: float = 0.5) -> tuple[bool, str]:
    """Whether holding frames ``start:stop`` decoded takes at most ``share`` of the memory available, and why not."""
    first = next(iter(sequence.frames(start, stop)), None)
    if first is None:
        return False, "no readable frame"
    need = (first.rgb.nbytes + first.depth.nbytes) * (stop - start) / 2**20
    available = memory_available_mib()
    if available is not None and need > share * available:
        return False, (f"holding {stop - start} decoded frames takes {need:.0f} MiB, over {share:.0%} of the "
                       f"{available:.0f} MiB available: bench fewer --frames to time like for like")
    return True, ""


class FramesInMemory:
    """A sequence whose frames ``start:stop`` were read and decoded once, before any clock started. ORB-SLAM3's
    examples time tracking on frames already in memory; the like-for-like ratio times ours the same way. Each pass
    hands out fresh :class:`~twohr.dataset.Frame` objects over the same arrays, so nothing cached by one run (the
    grey image) helps the next."""

    def __init__(self, sequence, start: int, stop: int) -> None:
        self._sequence = sequence
        self._arrays = {f.index: (f.stamp, f.rgb, f.depth) for f in sequence.frames(start, stop)}

    def frames(self, start: int = 0, stop: int | None = None, step: int = 1):
        """Frames in order, as :meth:`RGBDSequence.frames` (skipped frames stay skipped)."""
        from twohr.dataset import Frame

        for index in range(start, len(self) if stop is None else min(stop, len(self)), step):
            if index in self._arrays:
                stamp, rgb, depth = self._arrays[index]
                yield Frame(index, stamp, rgb, depth)

    def __len__(self) -> int:
        return len(self._sequence)

    def __getattr__(self, name: str):
        return getattr(self._sequence, name)


def orbslam3_run(sequence, start: int, stop: int, files: tuple[Path, Path]) -> dict:
    """ORB-SLAM3 RGB-D (pyorbslam3) on the same frames: ms per ``track_rgbd`` call (median and mean) and its
    trajectory's ATE. Frames are read before timing; only the tracking calls are timed, as ORB-SLAM3's own
    examples do."""
    import pyorbslam3

    slam = pyorbslam3.Slam(str(files[0]), str(files[1]), pyorbslam3.Sensor.RGBD)
    stamps, poses, ms = [], [], []
    try:
        for frame in sequence.frames(start, stop):
            raw_depth = (frame.depth * sequence.camera.depth_factor).astype(np.float32)
            t0 = time.perf_counter()
            result = slam.track_rgbd(frame.rgb, raw_depth, frame.stamp)
            ms.append((time.perf_counter() - t0) * 1000)
            if result.pose_valid:
                stamps.append(frame.stamp)
                poses.append(np.asarray(result.pose_wc, np.float64))
    finally:
        slam.shutdown()
    out = {"ms_per_frame": {**_percentiles(ms), "mean": round(float(np.mean(ms)), 2)},
           "tracked_percent": round(100 * len(poses) / max(1, len(ms)), 1)}
    if sequence.has_ground_truth() and len(poses) >= 3:
        extrinsic = sequence.default_gt_extrinsic()
        report, _ = evaluate(sequence.ground_truth(extrinsic), Trajectory(np.array(stamps), np.array(poses)),
                             gt_extrinsic=extrinsic)
        out["ate_rmse"] = round(report.ate.rmse, 4)
    return out


def throughput(sequence, config: PipelineConfig, frames: int = 60, start: int = 0, runs: int = 3,
               baseline: PipelineConfig | None = None, progress: bool = True) -> dict:
    """Run the pipeline ``runs`` times over the same frames; each run is paired with a run of ``baseline``
    (default: the ORB ablation) so that the ratio survives a noisy machine."""
    baseline = baseline or load_config(preset="orb")
    stop = min(len(sequence), start + frames)
    results = {"pipeline": [], "baseline": []}
    orbslam3 = orbslam3_files()
    orbslam3_runs: list[dict] = []
    in_memory: FramesInMemory | None = None
    fits, why_not = frames_fit_in_memory(sequence, start, stop) if orbslam3 is not None else (False, "")
    in_memory_ms: list[float] = []  # ours, wall ms per frame with the frames decoded before the clock
    ate_runs: list[float] = []
    in_memory_ate: list[float] = []
    stage_ms: dict[str, list[float]] = {"ms_detector": [], "ms_yolo": [], "ms_tracker": [], "ms_total": []}
    latency: dict[str, list[float]] = {"keyframe_frames": [], "other_frames": []}
    keyframe_ms: dict[str, list[float]] = {"ms_detector": [], "ms_yolo": [], "ms_mapping": [], "ms_job": [],
                                           "lag_frames": []}
    pipeline_rss = None
    chosen: dict = {}  # what the first run chose at warm-up (detector.model=auto: the network and its timings)

    def score(run, into: list[float]) -> None:
        if sequence.has_ground_truth() and len(run.trajectory) >= 3:
            extrinsic = sequence.default_gt_extrinsic()
            into.append(evaluate(sequence.ground_truth(extrinsic), run.trajectory, gt_extrinsic=extrinsic)[0].ate.rmse)

    for _ in range(runs):
        for label, conf in (("pipeline", config), ("baseline", baseline)):
            run = run_sequence(sequence, conf, start=start, stop=stop, progress=progress)
            results[label].append(len(run.stats) / run.wall_s)
            if label == "pipeline":
                chosen = chosen or run.chosen
                score(run, ate_runs)
                for key in stage_ms:
                    stage_ms[key] += [getattr(s, key) for s in run.stats]
                for s in run.stats:
                    latency["keyframe_frames" if s.keyframe else "other_frames"].append(s.ms_total)
                for job in run.keyframe_log:
                    for key in keyframe_ms:
                        keyframe_ms[key].append(getattr(job, key))
        if orbslam3 is not None:
            if pipeline_rss is None:  # the frames held in memory and ORB-SLAM3 in this process: our peak is before
                pipeline_rss = peak_rss_mib()
                in_memory = FramesInMemory(sequence, start, stop) if fits else None
            if in_memory is not None:
                run = run_sequence(in_memory, config, start=start, stop=stop, progress=progress)
                in_memory_ms.append(1000 * run.wall_s / max(1, len(run.stats)))
                score(run, in_memory_ate)
            orbslam3_runs.append(orbslam3_run(sequence if in_memory is None else in_memory, start, stop, orbslam3))
    fps = float(np.median(results["pipeline"]))
    base = float(np.median(results["baseline"]))
    comparison: dict[str, object] = {"orbslam3": "not run: pip install pyorbslam3 and put its vocabulary and "
                                                 "settings in ../shared/baselines (or set PYORBSLAM3_VOCAB)"}
    if orbslam3_runs:
        orb_ms = float(np.median([r["ms_per_frame"]["median"] for r in orbslam3_runs]))
        orb_mean_ms = float(np.median([r["ms_per_frame"]["mean"] for r in orbslam3_runs]))
        comparison = {"orbslam3": {
            "ms_per_frame_median": round(orb_ms, 2), "runs": orbslam3_runs,
            "ratio_ms_per_frame": round((1000 / fps) / orb_ms, 3),
            "note": "ours: wall time per frame over the whole run, the frames read and decoded during it; "
                    "ORB-SLAM3: the median of its track_rgbd calls on frames read before",
            "like_for_like": like_for_like(in_memory_ms, in_memory_ate, orb_mean_ms) if in_memory_ms else
            {"not_run": why_not}}}
    return {**comparison, "ate_rmse_runs": [round(a, 4) for a in ate_runs],
            "ate_rmse_median": round(float(np.median(ate_runs)), 4) if ate_runs else None,
        "sequence": sequence.name, "frames": stop - start, "runs": runs,
        "fps_median": round(fps, 3), "fps_runs": [round(f, 3) for f in results["pipeline"]],
        "baseline_fps_median": round(base, 3), "baseline": "ORB + mutual NN on the same tracker",
        "speed_ratio_to_baseline": round(fps / base, 4),
        "stages_ms": {k.removeprefix("ms_"): _percentiles(v) for k, v in stage_ms.items()},
        "per_frame_latency_ms": {k: _percentiles(v) for k, v in latency.items() if v},
        "keyframe_jobs": {k.removeprefix("ms_"): _percentiles(v) for k, v in keyframe_ms.items() if v},
        "mode": config.pipeline.mode, "chosen": chosen,
        "peak_rss_mib": round(pipeline_rss or peak_rss_mib(), 1),
        **({"peak_rss_mib_with_orbslam3": round(peak_rss_mib(), 1)} if pipeline_rss else {}),
        "machine": {**machine(), "platform": platform.platform()},
    }


def like_for_like(ours_ms: list[float], ours_ate: list[float], orbslam3_mean_ms: float) -> dict:
    """The like-for-like comparison's figures: our wall ms per frame and ATE per run, over frames held in memory,
    against ORB-SLAM3's mean ``track_rgbd`` ms on the same frames."""
    ours = float(np.median(ours_ms))
    return {"ours_ms_per_frame": round(ours, 2), "ours_runs": [round(m, 2) for m in ours_ms],
            "ours_ate_rmse_runs": [round(a, 4) for a in ours_ate],
            "ours_ate_rmse_median": round(float(np.median(ours_ate)), 4) if ours_ate else None,
            "orbslam3_ms_per_frame": round(orbslam3_mean_ms, 2),
            "ratio_ms_per_frame": round(ours / orbslam3_mean_ms, 3),
            "note": "both on the same frames decoded before the clock, both a mean over every frame: ours the run's "
                    "wall time per frame (waiting for its last keyframe jobs), ORB-SLAM3 the mean of its track_rgbd "
                    "calls (its local mapping runs on beside them)"}


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
    c0, t0 = time.process_time(), time.monotonic()
    for i in range(frames):
        if rate:
            time.sleep(max(0.0, t0 + i / rate - time.monotonic()))
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


@dataclass
class FrontCache:
    """Front-end outputs (keypoints, dynamic masks and their timings) of every frame in a range, kept in memory
    and shared between runs that differ only after the front end: keypoints by detector config, masks by yolo
    config. The one cache of the in-process studies (ablations, sensitivity, the tracker bench)."""

    keypoints: dict[tuple, dict[int, tuple]] = field(default_factory=dict)
    masks: dict[tuple, dict[int, tuple]] = field(default_factory=dict)

    def outputs(self, sequence, config: PipelineConfig, stop: int, progress: bool, start: int = 0,
                step: int = 1) -> dict[int, StageOutput]:
        """Frame index -> :class:`StageOutput` of frames ``start:stop:step``, running the networks only once."""
        frames = (start, stop, step)
        det_key = (config.detector.model_dump_json(), frames)
        yolo_key = (config.yolo.model_dump_json(), frames) if config.yolo.enabled else None
        need_det = det_key not in self.keypoints
        need_yolo = yolo_key is not None and yolo_key not in self.masks
        if need_det or need_yolo:
            from tqdm import tqdm

            front = FrontEnd(config)
            det, masks = self.keypoints.setdefault(det_key, {}), self.masks.setdefault(yolo_key, {})
            for frame in tqdm(sequence.frames(start, stop, step), total=len(range(start, stop, step)),
                              disable=not progress, unit="frame",
                              desc=f"front end {config.detector.features}{' + yolo' if yolo_key else ''}"):
                if need_det:
                    t0 = time.perf_counter()
                    det[frame.index] = (front.detector.detect(frame.rgb), (time.perf_counter() - t0) * 1000)
                if need_yolo:
                    t0 = time.perf_counter()
                    regions = front.masker(frame.rgb, frame.depth)
                    masks[frame.index] = (regions.mask, len(regions.dynamic), (time.perf_counter() - t0) * 1000)
        out = {}
        for index, (kp, ms_det) in self.keypoints[det_key].items():
            mask, objects, ms_yolo = self.masks[yolo_key][index] if yolo_key else (None, 0, 0.0)
            out[index] = StageOutput(kp, mask, objects, ms_det, ms_yolo)
        return out


def ablations(sequence, base: PipelineConfig, variants: dict[str, dict] | None = None, stop: int | None = None,
              repeats: int = 3, progress: bool = True) -> list[dict]:
    """ATE RMSE, S.D., % of frames tracked and ms/frame for each variant on one sequence.

    The networks are deterministic, so each front end runs once; the tracker runs twice, and where
    the two runs differ it runs ``repeats`` times and the median is reported."""
    variants = variants or ABLATIONS
    stop = len(sequence) if stop is None else min(stop, len(sequence))
    gt = sequence.ground_truth(sequence.default_gt_extrinsic())
    cache = FrontCache()
    rows = []
    for name, overrides in variants.items():
        config = load_config(None, merge_overrides(base.model_dump(mode="json"), overrides))
        config.pipeline.mode = "every_frame"  # the variants share cached front-end outputs of every frame
        fronts = cache.outputs(sequence, config, stop, progress)

        def once(config=config, fronts=fronts):
            run = run_sequence(sequence, config, stop=stop, progress=False, front_cache=fronts)
            for row in run.stats:  # the networks ran once, into the cache: their time is the cached one
                front = fronts[row.index]
                row.ms_detector, row.ms_yolo = front.ms_detector, front.ms_yolo
                row.ms_total += front.ms_detector + front.ms_yolo
            report, _ = evaluate(gt, run.trajectory, gt_extrinsic=sequence.default_gt_extrinsic())
            return report.ate.rmse, report.ate.std, run

        runs = [once(), once()]
        deterministic = np.allclose(runs[0][2].trajectory.poses, runs[1][2].trajectory.poses)
        if not deterministic:
            runs += [once() for _ in range(repeats - 2)]
        rmse = [r[0] for r in runs]
        pick = runs[int(np.argsort(rmse)[len(rmse) // 2])]
        run = pick[2]
        rows.append({
            "variant": name, "ate_rmse": round(float(np.median(rmse)), 4), "ate_std": round(pick[1], 4),
            "runs": 1 if deterministic else len(runs), "deterministic": deterministic,
            "tracked_percent": round(run.tracked_percent, 1),
            "ms_per_frame": round(float(np.median([s.ms_total for s in run.stats])), 1),
            "ms_detector": round(float(np.median([s.ms_detector for s in run.stats])), 1),
            "ms_yolo": round(float(np.median([s.ms_yolo for s in run.stats])), 1),
            "ms_tracker": round(float(np.median([s.ms_tracker for s in run.stats])), 1),
        })
    return rows


def static_camera_row(sequence) -> dict:
    """The sanity baseline: a camera that never moves."""
    from twohr.evaluation import static_trajectory

    report, _ = evaluate(sequence.ground_truth(sequence.default_gt_extrinsic()), static_trajectory(sequence.stamps),
                         gt_extrinsic=sequence.default_gt_extrinsic())
    return {"variant": "static camera (sanity)", "ate_rmse": round(report.ate.rmse, 4),
            "ate_std": round(report.ate.std, 4), "runs": 1, "deterministic": True, "tracked_percent": 100.0,
            "ms_per_frame": 0.0}


def format_table(rows: list[dict]) -> str:
    lines = ["| variant | ATE RMSE (m) | S.D. (m) | tracked % | ms/frame | runs |", "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['variant']} | {r['ate_rmse']:.4f} | {r['ate_std']:.4f} | {r['tracked_percent']:.1f} | "
                     f"{r['ms_per_frame']:.0f} | {r['runs']}{'' if r['deterministic'] else ' (median)'} |")
    return "\n".join(lines)


def session_latency(bus, gateway_url: str, sequence_name: str, frames: int = 60, rate: float = 0.0,
                    config_overrides: dict | None = None, record: bool = False, robot_id: str = "bench",
                    timeout: float = 600.0, api_token: str | None = None, verify: object = True) -> dict:
    """Run one session on an already-running system (``twohr up`` or the compose stack) and measure it
    from outside: an independent Zenoh client (``bus``, a BusConfig with client credentials) receives the
    poses while ``POST /sessions`` on ``gateway_url`` drives the run. Frame -> pose latency is pose arrival
    minus the source's send time (same host clock)."""
    import threading

    import httpx

    from twohr import keys
    from twohr.bus import open_session
    from twohr.messages import PoseMsg, StatusMsg, decode

    received: list[tuple[float, PoseMsg]] = []
    keyframe_jobs: dict[str, dict[str, int]] = {}  # session id -> the tracker's keyframe job latency
    lock = threading.Lock()

    def on_pose(sample) -> None:
        now = time.time()
        pose, _ = decode(sample.payload.to_bytes(), PoseMsg)
        with lock:
            received.append((now, pose))

    def on_status(sample) -> None:
        status, _ = decode(sample.payload.to_bytes(), StatusMsg)
        if status.service == "tracker" and status.state == "keyframe_jobs":
            keyframe_jobs[status.session_id] = status.counters

    listener = open_session(bus)
    sub = listener.declare_subscriber(keys.all_robots("pose"), on_pose)
    status_sub = listener.declare_subscriber(keys.all_robots("status"), on_status)
    headers = {"Authorization": f"Bearer {api_token}"} if api_token else {}
    try:
        with httpx.Client(base_url=gateway_url, timeout=30, headers=headers, verify=verify) as client:
            response = client.post("/sessions", json={"sequence": sequence_name, "robot_id": robot_id,
                                                      "max_frames": frames, "rate": rate, "record": record,
                                                      "config": config_overrides or {}})
            response.raise_for_status()
            session_id = response.json()["id"]
            deadline = time.time() + timeout
            while (info := client.get(f"/sessions/{session_id}").json())["state"] in ("starting", "running"):
                if time.time() > deadline:
                    raise TimeoutError(f"session {session_id} did not finish within {timeout:.0f} s")
                time.sleep(0.2)
            time.sleep(0.5)  # the listener's last samples may still be in flight
    finally:
        sub.undeclare()
        status_sub.undeclare()
        listener.close()
    with lock:
        mine = sorted(((t, p) for t, p in received if p.session_id == session_id), key=lambda tp: tp[0])
    latencies = [1000 * (t - p.frame_sent_at) for t, p in mine]
    # throughput once the session runs: the first pose waits for the first map (and a replay at a rate waits for
    # it before it plays on), which first_pose_s reports apart
    span = mine[-1][0] - mine[0][0] if len(mine) > 1 else float("nan")
    first_pose_s = mine[0][0] - min(p.frame_sent_at for _, p in mine) if mine else None
    sent = int(info.get("frames_sent") or frames)  # "frames" in the session info counts poses received
    return {"session": info, "frames": len(mine), "frame_indices": [p.frame_index for _, p in mine],
            "rate": rate, "dropped_percent": round(100 * (1 - len({p.frame_index for _, p in mine}) / max(1, sent)), 2),
            "latency_ms": {"p50": round(float(np.percentile(latencies, 50)), 1) if mine else None,
                           "p99": round(float(np.percentile(latencies, 99)), 1) if mine else None},
            "fps": round((len(mine) - 1) / span, 3) if len(mine) > 1 else 0.0,
            "first_pose_s": round(first_pose_s, 2) if first_pose_s is not None else None,
            "keyframe_jobs": keyframe_jobs.get(session_id, {})}


def bus_latency(sequence_root, config_overrides: dict, frames: int = 60, rate: float = 0.0,
                timeout: float = 600.0, robots: int = 1) -> dict:
    """Frame -> pose latency (p50, p99) and throughput of the whole system over Zenoh (``twohr up`` as
    local processes), for the same frames and config as an in-process run. ``robots`` > 1: that many robots
    replay the sequence at once through the one stack (one detector, yolo and matcher service for all); the
    figures are per robot (``per_robot``), the top-level ones their medians, and ``served_at_rate`` counts the
    robots that kept at least 29/30 of the source's rate with at most 2 % of their frames dropped."""
    import tempfile

    from twohr.bus import free_port
    from twohr_app.supervisor import start_system

    router, port = f"tcp/127.0.0.1:{free_port()}", free_port()
    recordings = tempfile.mkdtemp(prefix="twohr_bench_")
    t_start = time.time()
    system = start_system(router, [str(sequence_root.parent)], recordings, "127.0.0.1", port)
    startup_s = time.time() - t_start
    try:
        if robots == 1:
            result = session_latency(system.bus(), f"http://127.0.0.1:{port}", sequence_root.name, frames, rate,
                                     config_overrides, timeout=timeout)
            return {"startup_s": round(startup_s, 1), **latency_summary(result)}
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(robots) as pool:
            per_robot = list(pool.map(lambda i: latency_summary(session_latency(
                system.bus(), f"http://127.0.0.1:{port}", sequence_root.name, frames, rate, config_overrides,
                robot_id=f"bench{i}", timeout=timeout)), range(robots)))
    finally:
        system.stop()
    summary = {key: float(np.median([r[key] for r in per_robot])) for key in ("frames", "dropped_percent", "fps")}
    firsts = [r["first_pose_s"] for r in per_robot if r["first_pose_s"] is not None]
    summary["first_pose_s"] = round(float(np.median(firsts)), 2) if firsts else None
    summary["latency_ms"] = {p: float(np.median([r["latency_ms"][p] or np.nan for r in per_robot]))
                             for p in ("p50", "p99")}
    camera_fps = 30 * rate if rate > 0 else 0  # rate 1 = the dev sequence's camera, 30 Hz; 0 = as fast as it goes
    served = sum(r["fps"] >= 29 / 30 * camera_fps and r["dropped_percent"] <= 2 for r in per_robot)
    return {"startup_s": round(startup_s, 1), "robots": robots, "rate": rate, **summary, "served_at_rate": served,
            "per_robot": per_robot}


def keyframe_job_medians(bus_runs: list[dict]) -> dict[str, float | None]:
    """The median over bus runs (and their robots) of the tracker's keyframe job latency, p50 and p90 (ms)."""
    reports = [robot.get("keyframe_jobs", {}) for run in bus_runs for robot in run.get("per_robot", [run])]
    return {key: float(np.median(found)) if (found := [r[key] for r in reports if key in r]) else None
            for key in ("ms_job_median", "ms_job_p90")}


def latency_summary(result: dict) -> dict:
    """The numbers of a :func:`session_latency` result, without the per-frame detail."""
    return {k: result[k] for k in ("frames", "rate", "dropped_percent", "latency_ms", "fps", "first_pose_s",
                                   "keyframe_jobs")}
