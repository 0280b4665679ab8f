"""``twohr bench --fleet N``: how many robots that track themselves one server's network services carry.

A robot with its own tracker (at the edge) sends the server only its keyframe jobs: the 2HR detection of a keyframe
(with its dynamic mask), the matches against its local map, and every few frames a dynamic mask alone. This bench
records those jobs from one real run of the pipeline over the sequence (:func:`record_jobs`: each call the schedule
made of the detector, yolo and matcher, with its frame's camera time), then replays them for N robots at once
against a stack's detector, yolo and matcher replicas over the bus, each robot on its own thread and at the
recorded times (robots start spread over one second), as N edge trackers would send them: a keyframe job's
detection and mask at once, then its matches, one job after another; the masks alone on a thread of their own. It
reports each robot's keyframe job latency (p50, p99) from the job's recorded time to its last answer, so that a
server falling behind the robots' rate shows as jobs waiting for the one before; how long a job took once sent; and
the server's CPU by service, and finds the largest n <= N whose every robot's p99 stays within ``P99_LIMIT_MS``
(N first; where N fails, smaller n by bisection)."""

from __future__ import annotations

import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twohr import keys
from twohr.config import PipelineConfig
from twohr.dataset import Frame, RGBDSequence
from twohr.rates import ReplayPacer

#: a fleet of n robots is carried while every robot's keyframe jobs come back within this, 99 times in 100 (ms)
P99_LIMIT_MS = 1000.0
#: robots start spread over this long (s), as robots switched on one after another would
SPREAD_S = 1.0


@dataclass
class Call:
    """One call a schedule made of a network service: which (its query key), for which frame, and, for a match
    query, its arrays."""

    query: str
    frame: int
    stamp: float
    arrays: dict[str, np.ndarray] | None = None
    reference: str = ""


@dataclass
class Job:
    """What one robot sends the server at once: a keyframe job (detection, its mask, then its matches) or a dynamic
    mask alone; ``at``: seconds after the robot's first frame."""

    kind: str  # "keyframe" or "mask"
    frame: int
    at: float
    calls: list[Call] = field(default_factory=list)


def record_jobs(sequence: RGBDSequence, config: PipelineConfig, start: int = 0, frames: int | None = None,
                progress: bool = True) -> list[Job]:
    """The network calls the keyframe schedule makes over ``frames`` frames of ``sequence`` from ``start`` (the
    networks run in this process, as ``twohr run`` runs them), grouped into the jobs an edge tracker sends."""
    from tqdm import tqdm

    from twohr_app.pipeline import local_stages
    from twohr_services.tracker.schedule import build_schedule
    from twohr_services.tracker.stages import Stages

    local = local_stages(config, sequence.camera)
    calls: list[Call] = []
    lock = threading.Lock()  # the mapping, mask and loop workers call from their threads

    def note(call: Call) -> None:
        with lock:
            calls.append(call)

    def detect(frame: Frame):
        note(Call(keys.DETECT_QUERY, frame.index, frame.stamp))
        return local.detect(frame)

    def mask(frame: Frame):
        note(Call(keys.DYNAMICS_QUERY, frame.index, frame.stamp))
        return local.dynamic_mask(frame)

    def match(frame: Frame, desc_a: np.ndarray, desc_b: np.ndarray):
        note(Call(keys.MATCH_QUERY, frame.index, frame.stamp, {"desc_a": desc_a, "desc_b": desc_b}, "local map"))
        return local.match(frame, desc_a, desc_b)

    def match_sets(frame: Frame, desc_a: np.ndarray, sets: list[np.ndarray]):
        sizes = np.array([len(s) for s in sets], np.int64)
        note(Call(keys.MATCH_QUERY, frame.index, frame.stamp,
                  {"desc_a": desc_a, "desc_b": np.concatenate(sets), "desc_b_sizes": sizes}, "candidate keyframes"))
        return [local.match(frame, desc_a, desc_b) for desc_b in sets]

    recording = Stages(detect, mask if local.dynamic_mask is not None else None, match, match_sets=match_sets)
    schedule = build_schedule(config, sequence.camera, recording, live=True)
    stop = len(sequence) if frames is None else min(len(sequence), start + frames)
    # at the camera's pace, as a robot's tracker runs: its workers take the keyframes they have time for
    pacer = ReplayPacer(speed=1)
    try:
        for frame in tqdm(sequence.frames(start, stop), total=stop - start, disable=not progress, unit="frame",
                          desc="recording keyframe jobs", dynamic_ncols=True):
            pacer.wait(frame.stamp)
            schedule.process(frame)
        schedule.finish()
    finally:
        schedule.close()
    return group_jobs(calls)


def group_jobs(calls: list[Call]) -> list[Job]:
    """Calls as jobs: a frame that was detected is a keyframe job (its detection, its mask where one was asked, its
    matches); a mask asked for another frame is a mask job; a match for a frame not detected (a loop's check) joins
    the latest keyframe job. Ordered by time."""
    if not calls:
        return []
    first = min(call.stamp for call in calls)
    detected = {call.frame for call in calls if call.query == keys.DETECT_QUERY}
    keyframes: dict[int, Job] = {}
    masks: list[Job] = []
    latest: Job | None = None
    for call in calls:
        if call.frame in detected:
            job = keyframes.setdefault(call.frame, Job("keyframe", call.frame, call.stamp - first))
            if call.query != keys.DYNAMICS_QUERY or not any(c.query == call.query for c in job.calls):
                job.calls.append(call)
            latest = job
        elif call.query == keys.DYNAMICS_QUERY:
            masks.append(Job("mask", call.frame, call.stamp - first, [call]))
        elif latest is not None:
            latest.calls.append(call)
    return sorted([*keyframes.values(), *masks], key=lambda job: job.at)


class RobotReplay:
    """One robot's recorded jobs sent to the stack's replicas at their times, from its own session."""

    def __init__(self, bus_session, robot: str, session_id: str, jobs: list[Job], sequence: RGBDSequence) -> None:
        from twohr.replicas import Replicas

        self.robot, self.session_id, self.jobs = robot, session_id, jobs
        self.replicas = {name: Replicas(bus_session, name) for name in keys.NETWORK_SERVICES}
        self.frames = self._frame_payloads(sequence, {c.frame for j in jobs for c in j.calls if c.arrays is None})
        self.latency_ms: dict[str, list[float]] = {"keyframe": [], "mask": []}  # from when it was due to its answer
        self.service_ms: list[float] = []  # keyframe jobs, from when they were sent
        self.late_ms: list[float] = []
        self.errors = 0

    def _frame_payloads(self, sequence: RGBDSequence, frames: set[int]) -> dict[int, bytes]:
        """The frame messages this robot sends (as its camera's source encodes them), made before the clock."""
        from twohr_services.source.core import frame_payloads

        return {index: next(frame_payloads(sequence, self.session_id, self.robot, start=index, max_frames=1)).payload
                for index in sorted(frames)}

    def _ask(self, call: Call) -> None:
        from twohr.messages import MatchRequestMsg, colour_image, encode

        service = SERVICE_OF[call.query]
        if call.arrays is None:  # the detector reads the colour image alone, as the tracker sends it
            payload = colour_image(self.frames[call.frame]) if service == "detector" else self.frames[call.frame]
        else:
            request = MatchRequestMsg(session_id=self.session_id, robot_id=self.robot, frame_index=call.frame,
                                      stamp=call.stamp, reference=call.reference)
            payload = encode(request, call.arrays)
        self.replicas[service].call(self.robot, call.query, payload, timeout=30.0)

    def _run_job(self, job: Job, pool: ThreadPoolExecutor) -> None:
        images = [c for c in job.calls if c.arrays is None]  # detection and mask at once, as the mapper asks them
        asked = [pool.submit(self._ask, call) for call in images[1:]]
        if images:
            self._ask(images[0])
        for future in asked:
            future.result()
        for call in job.calls:
            if call.arrays is not None:
                self._ask(call)

    def run(self, start_at: float, kind: str) -> None:
        """Send this robot's jobs of ``kind`` one after another, each at its time or as soon as the one before
        it is answered."""
        with ThreadPoolExecutor(2, thread_name_prefix=f"{self.robot}-{kind}") as pool:
            for job in (j for j in self.jobs if j.kind == kind):
                due = start_at + job.at
                time.sleep(max(0.0, due - time.monotonic()))
                began = time.monotonic()
                self.late_ms.append((began - due) * 1000)
                try:
                    self._run_job(job, pool)
                except Exception:  # a job no replica answered: counted, the robot goes on
                    self.errors += 1
                    continue
                self.latency_ms[kind].append((time.monotonic() - due) * 1000)
                if kind == "keyframe":
                    self.service_ms.append((time.monotonic() - began) * 1000)

    def close(self) -> None:
        for replicas in self.replicas.values():
            replicas.close()


def _percentile(values: list[float], q: float) -> float | None:
    return round(float(np.percentile(values, q)), 1) if values else None


def replay(system, url: str, sequence: RGBDSequence, jobs: list[Job], robots: int,
           config_overrides: dict | None = None) -> dict:
    """``robots`` robots' jobs at once against ``system``'s network services (a session each, started over HTTP so
    that every service knows its config); their latencies and the server's CPU by service."""
    import httpx

    from twohr.bus import open_session

    from .camera_sessions import process_cpu_s

    names = [f"fleet-{i + 1}" for i in range(robots)]
    bus = open_session(system.bus("tracker"))  # the bench speaks to the networks as the trackers do
    sessions, replays = {}, []
    try:
        with httpx.Client(base_url=url, timeout=60) as http:
            for name in names:
                created = http.post("/sessions", json={"source": "camera", "robot_id": name, "record": False,
                                                       "config": config_overrides or {}})
                created.raise_for_status()
                sessions[name] = created.json()["id"]
            replays = [RobotReplay(bus, name, sessions[name], jobs, sequence) for name in names]
            time.sleep(0.5)  # every service has taken the sessions' starts
            cpu0, t0 = process_cpu_s(system), time.monotonic()
            threads = [threading.Thread(target=r.run, args=(t0 + SPREAD_S * i / robots, kind), daemon=True)
                       for i, r in enumerate(replays) for kind in ("keyframe", "mask")]
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join()
            wall = time.monotonic() - t0
            cpu1 = process_cpu_s(system)
            for name in names:
                http.delete(f"/sessions/{sessions[name]}")
    finally:
        for r in replays:
            r.close()
        bus.close()
    cores = {name: round((cpu1.get(name, 0.0) - cpu0.get(name, 0.0)) / wall, 2) for name in cpu1}
    network = sum(v for name, v in cores.items() if name.split("-")[0] in keys.NETWORK_SERVICES)
    return {"robots": robots, "wall_s": round(wall, 1),
            "keyframe_jobs": [len(r.latency_ms["keyframe"]) for r in replays],
            "keyframe_ms_p50": [_percentile(r.latency_ms["keyframe"], 50) for r in replays],
            "keyframe_ms_p99": [_percentile(r.latency_ms["keyframe"], 99) for r in replays],
            "keyframe_service_ms_p50": [_percentile(r.service_ms, 50) for r in replays],
            "mask_ms_p50": [_percentile(r.latency_ms["mask"], 50) for r in replays],
            "started_late_ms_p99": [_percentile(r.late_ms, 99) for r in replays],
            "failed_jobs": [r.errors for r in replays],
            "server_cores": cores, "network_cores": round(network, 2)}


def carried(run: dict) -> bool:
    """Whether every robot of a run kept its keyframe jobs within the limit and none failed."""
    return not any(run["failed_jobs"]) and all(p is not None and p <= P99_LIMIT_MS for p in run["keyframe_ms_p99"])


#: which service answers each query
SERVICE_OF = {keys.DETECT_QUERY: "detector", keys.DYNAMICS_QUERY: "yolo", keys.MATCH_QUERY: "matcher"}


def on_server(jobs: list[Job], server_stages: tuple[str, ...]) -> list[Job]:
    """The jobs as the server sees them when a robot runs the networks not in ``server_stages`` itself (``twohr
    camera --edge --server-stages``): their other calls gone, and jobs left with none."""
    kept = [Job(job.kind, job.frame, job.at, [c for c in job.calls if SERVICE_OF[c.query] in server_stages])
            for job in jobs]
    return [job for job in kept if job.calls]


def fleet_bench(sequence: RGBDSequence, config: PipelineConfig, robots: int, frames: int | None = None,
                start: int = 0, replicas: dict[str, int] | None = None, config_overrides: dict | None = None,
                progress: bool = True, server_stages: tuple[str, ...] = tuple(keys.NETWORK_SERVICES)) -> dict:
    """``twohr bench --fleet N`` (see the module docstring): the recorded jobs, the run of N robots, the smaller runs
    where it failed, and the largest n carried. ``server_stages``: the networks the server runs for the robots (the
    default, all three; ``twohr camera --edge``'s default, the detector alone)."""
    from twohr.bus import free_port
    from twohr.machine import machine
    from twohr_app.supervisor import start_system

    jobs = on_server(record_jobs(sequence, config, start, frames, progress), server_stages)
    kinds = {kind: sum(job.kind == kind for job in jobs) for kind in ("keyframe", "mask")}
    if progress:
        print(f"recorded {kinds['keyframe']} keyframe jobs and {kinds['mask']} masks over "
              f"{jobs[-1].at if jobs else 0:.1f} s of frames", flush=True)
    router, port = f"tcp/127.0.0.1:{free_port()}", free_port()
    with tempfile.TemporaryDirectory(prefix="twohr-fleet-") as scratch:
        system = start_system(router, [str(sequence.root.parent)], str(Path(scratch) / "recordings"), "127.0.0.1",
                              port, timeout=300, max_robots=float(robots),
                              replicas={"tracker": 1} | (replicas or {}))  # the robots track themselves
        try:
            runs: dict[int, dict] = {}

            def run(n: int) -> bool:
                runs[n] = replay(system, f"http://127.0.0.1:{port}", sequence, jobs, n, config_overrides)
                if progress:
                    print(f"{n} robot(s): keyframe job p99 {runs[n]['keyframe_ms_p99']} ms, network services "
                          f"{runs[n]['network_cores']} cores", flush=True)
                return carried(runs[n])

            low, high = 0, robots  # low: carried (0: none yet), high: the smallest n known not carried
            if run(robots):
                low = robots
            while high - low > 1:
                middle = (low + high) // 2
                low, high = (middle, high) if run(middle) else (low, middle)
        finally:
            system.stop()
    return {"robots": robots, "keyframe_p99_ms": runs[robots]["keyframe_ms_p99"], "max_robots": low,
            "p99_limit_ms": P99_LIMIT_MS, "frames": frames or len(sequence) - start, "recorded": kinds,
            "server_stages": list(server_stages),
            "replicas": {name: 1 for name in keys.NETWORK_SERVICES} | (replicas or {}),
            "runs": [runs[n] for n in sorted(runs)], "machine": machine()}


def format_table(result: dict) -> str:
    lines = ["| robots | keyframe jobs per robot | keyframe p50 ms | keyframe p99 ms | answered in, p50 ms | mask p50 "
             "ms | started late p99 ms | network services (cores) | carried |", "|---|---|---|---|---|---|---|---|---|"]
    for run in result["runs"]:
        lines.append(f"| {run['robots']} | {_span(run['keyframe_jobs'])} | {_span(run['keyframe_ms_p50'])} | "
                     f"{_span(run['keyframe_ms_p99'])} | {_span(run['keyframe_service_ms_p50'])} | "
                     f"{_span(run['mask_ms_p50'])} | "
                     f"{_span(run['started_late_ms_p99'])} | {run['network_cores']} | "
                     f"{'yes' if carried(run) else 'no'} |")
    machine = result["machine"]
    lines += ["", f"max robots with every keyframe p99 <= {result['p99_limit_ms']:.0f} ms: {result['max_robots']} "
              f"({machine['cpu_model']}, {machine['cpus']} CPUs, AMX {'yes' if machine['amx'] else 'no'}; the "
              f"server runs {', '.join(result.get('server_stages', keys.NETWORK_SERVICES))})"]
    return "\n".join(lines)


def _span(values: list[float | None]) -> str:
    known = [v for v in values if v is not None]
    return "–" if not known else f"{min(known):g}" if min(known) == max(known) else f"{min(known):g}–{max(known):g}"
