"""Two live robots building one map at once (``twohr bench --share``): the figures of the co-mapping docs.

Each run starts two robots that track themselves (``twohr camera --edge``) at 30 Hz on one stack with a map store,
both sharing a new map (``lab1``, ``lab2``... one per run): robot ``a`` replays the sequence's frames 0-319, robot
``b`` frames 0-399 of its backwards variant (the frames 559 down to 160 of a 560-frame sequence), so that b walks
over ground a maps. Per run: when b was merged (seconds after its session started, its keyframe count), the map
server's search that merged it (ms) and its CPU over the run, the bytes each robot sent the map server and got back,
the bytes of b's path sent again in the map's frame (the correction), the frames each robot had posed in the map's
frame, and the joint ATE (each robot's refined trajectory against its own ground truth, one SE(3) Umeyama
alignment over both, 0.02 s association) beside each robot's own; and every stack service's RSS after each run.
"""

from __future__ import annotations

import tempfile
import threading
import time
from pathlib import Path

FRAMES_A, FRAMES_B = 320, 400


class _Listener:
    """What the bus says of the shared maps while the runs go: the map server's statuses and the robots' paths."""

    def __init__(self) -> None:
        self.statuses: list = []
        self.paths: list[tuple[float, str, int, bool, str]] = []  # (time, robot, bytes, full, frame)
        self.lock = threading.Lock()

    def status(self, sample) -> None:
        from twohr.messages import StatusMsg, decode

        message, _ = decode(sample.payload.to_bytes(), StatusMsg)
        if message.service == "mapserver":
            with self.lock:
                self.statuses.append(message)

    def path(self, sample) -> None:
        from twohr.messages import PathMsg, split

        payload = sample.payload.to_bytes()
        message, _ = split(payload, PathMsg)
        if not message.final:
            with self.lock:
                self.paths.append((time.time(), message.robot_id, len(payload), message.full, message.frame_id))


def share_runs(sequence, runs: int = 3, progress: bool = True) -> list[dict]:
    """``runs`` two-robot share runs on one stack (see the module docstring); one row per run."""
    from twohr import keys
    from twohr.bus import free_port, open_session
    from twohr.dataset import RGBDSequence
    from twohr.evaluation import joint_ate
    from twohr_app.supervisor import start_system

    from ...tracking.backwards import backwards
    from .camera_sessions import _stack, camera_session, process_cpu_s, rss_mib

    rows = []
    with tempfile.TemporaryDirectory(prefix="twohr-share-") as scratch:
        scratch = Path(scratch)
        robots = {"a": (sequence, FRAMES_A), "b": (RGBDSequence(backwards(sequence.root, scratch)), FRAMES_B)}
        router, port = f"tcp/127.0.0.1:{free_port()}", free_port()
        system = start_system(router, [str(sequence.root.parent)], str(scratch / "recordings"), "127.0.0.1", port,
                              timeout=300, max_robots=2, maps=str(scratch / "maps"))
        try:
            stacks = {robot: _stack(system, scratch, router, port, robot, None, edge=True) for robot in robots}
            listener = _Listener()
            observer = open_session(stacks["a"].observer)
            subscribers = [observer.declare_subscriber(keys.all_robots("status"), listener.status),
                           observer.declare_subscriber(keys.all_robots("path"), listener.path)]
            for run in range(runs):
                name = f"lab{run + 1}"
                if progress:
                    print(f"run {run + 1} of {runs}: robots a and b share map {name}", flush=True)
                cpu0, started, found = process_cpu_s(system), threading.Event(), {}

                def one(robot: str, name=name, started=started, found=found) -> None:
                    sequence_r, frames = robots[robot]
                    found[robot] = camera_session(stacks[robot], sequence_r, robot, frames, busy=0, progress=False,
                                                  map_request={"name": name, "mode": "share"},
                                                  posted=started if robot == "a" else None,
                                                  post_after=started if robot == "b" else None)

                threads = [threading.Thread(target=one, args=(robot,)) for robot in robots]
                for thread in threads:
                    thread.start()
                for thread in threads:
                    thread.join(600)
                deadline = time.monotonic() + 60
                while time.monotonic() < deadline:  # the map server's last word on the run's sessions
                    with listener.lock:
                        shared = {s.session_id: s for s in listener.statuses if s.state == "shared"}
                    if all(found[r]["session_id"] in shared for r in found):
                        break
                    time.sleep(0.5)
                cpu = process_cpu_s(system)
                rows.append(_row(name, robots, found, shared, listener, cpu.get("mapserver", 0) - cpu0.get(
                    "mapserver", 0), system, port, joint_ate))
                rows[-1]["stack_rss_mib"] = {child.name: rss_mib(child.proc.pid)  # after the run: growth over runs
                                             for child in system.group.children}
                if progress:
                    print(format_table(rows[-1:]), flush=True)
            for subscriber in subscribers:
                subscriber.undeclare()
            observer.close()
        finally:
            system.stop()
    return rows


def _row(name: str, robots: dict, found: dict, shared: dict, listener: _Listener, mapserver_cpu_s: float, system,
         port: int, joint_ate) -> dict:
    import httpx

    from twohr.trajectory import parse_tum

    pairs, posed = [], {}
    for robot, row in found.items():
        sequence, frames = robots[robot]
        served = parse_tum(row["served_tum"], f"robot {robot}'s served trajectory")
        posed[robot] = round(100 * len(served) / frames, 1)
        pairs.append((sequence.ground_truth(sequence.default_gt_extrinsic()), served))
    ate, each = joint_ate(pairs)
    info = {s["robot_id"]: s for s in httpx.get(f"http://127.0.0.1:{port}/sessions", timeout=30).json()
            if s["id"] in (found["a"]["session_id"], found["b"]["session_id"])}
    merge = found["b"]["merge"] or {}
    merged_at = merge.get("at")
    with listener.lock:  # b's first whole path in the map's frame after its merge: the correction
        correction = next((size for at, robot, size, full, frame in listener.paths
                           if robot == "b" and full and frame == name and merged_at and at >= merged_at), None)
    counters = {robot: shared.get(found[robot]["session_id"]).counters if found[robot]["session_id"] in shared
                else {} for robot in found}
    return {
        "map": name, "merged": merge.get("kind") == "merged",
        "merge_s_after_start": round(merged_at - info["b"]["created"], 2) if merged_at else None,
        "merge_keyframe": merge.get("keyframes"), "refinements": merge.get("refinements"),
        "merge_inliers": merge.get("inliers"), "merge_search_ms": merge.get("ms"),
        "mapserver_cpu_s": round(mapserver_cpu_s, 2),
        "bytes_to_mapserver": {r: c.get("bytes_in") for r, c in counters.items()},
        "bytes_from_mapserver": {r: c.get("bytes_out") for r, c in counters.items()},
        "correction_path_bytes": correction,
        "posed_in_map_percent": posed, "joint_ate": round(ate, 4),
        "joint_ate_each": {r: round(v, 4) for r, v in zip(found, each, strict=True)},
        "own_ate": {r: found[r]["ate_served"] for r in found},
    }


def format_table(rows: list[dict]) -> str:
    """The runs as a Markdown table."""
    lines = ["| map | b merged after | at b's keyframe | search ms | map server CPU s | bytes to / from the map "
             "server (a; b) | correction bytes | posed in the map's frame % (a / b) | joint ATE m | own ATE a / b |",
             "|---" * 10 + "|"]
    for r in rows:
        to, back = r["bytes_to_mapserver"], r["bytes_from_mapserver"]
        lines.append(f"| {r['map']} | {r['merge_s_after_start']} s | {r['merge_keyframe']} | {r['merge_search_ms']} | "
                     f"{r['mapserver_cpu_s']} | {to.get('a')} / {back.get('a')}; {to.get('b')} / {back.get('b')} | "
                     f"{r['correction_path_bytes']} | {r['posed_in_map_percent'].get('a')} / "
                     f"{r['posed_in_map_percent'].get('b')} | {r['joint_ate']} | {r['own_ate'].get('a')} / "
                     f"{r['own_ate'].get('b')} |")
    return "\n".join(lines)
