"""Sessions over Zenoh measured from outside: frame -> pose latency and FPS of ``twohr up`` or a running stack."""

from __future__ import annotations

import time

import numpy as np


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
