"""Live camera sessions under field conditions: the camera check with busy processes beside it, and soak runs.

``twohr bench --live`` starts ``twohr up`` (local processes, ROS 2 bridge on), then for each count of busy processes
(``--busy 0,1,2``: ``python3 -c 'while True: pass'`` beside the stack) runs a camera session fed by ``twohr camera
--replay SEQ --rate 30`` for ``--frames`` frames, ends it with DELETE, downloads the trajectory it serves (refined)
and the online one, and scores both. ``twohr bench --soak MINUTES`` runs one camera session on the sequence looped
at 30 Hz and samples every service's RSS and the session's FPS as it goes.

Per session it reports frames posed, dropped, FPS, frame->pose latency p50/p99 (pose received minus the frame's
send time), the ATE of the served and the online trajectory (SE(3), 0.02 s, camera-frame GT), the session's health
as its status said, and each service's RSS.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

#: a busy process of the robot's own (its navigation stack, a browser): one core's worth of work at normal priority
BUSY_LOOP = "while True: pass"


def rss_mib(pid: int) -> float | None:
    """Resident memory of a process in MiB (None once it has gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


@dataclass
class PoseLog:
    """Poses of one robot as they arrive: frame index, receive time and the frame's send time."""

    received: list[tuple[int, float, float]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __call__(self, sample) -> None:
        from twohr.messages import PoseMsg, decode

        pose, _ = decode(sample.payload.to_bytes(), PoseMsg)
        with self.lock:
            self.received.append((pose.frame_index, time.time(), pose.frame_sent_at))

    def latency_ms(self) -> np.ndarray:
        with self.lock:
            return np.array([(r - s) * 1000 for _, r, s in self.received if s > 0])


def _busy(count: int) -> list[subprocess.Popen]:
    return [subprocess.Popen([sys.executable, "-c", BUSY_LOOP]) for _ in range(count)]


def _score(sequence, text: str) -> float | None:
    from twohr.evaluation import evaluate
    from twohr.trajectory import parse_tum

    trajectory = parse_tum(text, "the served trajectory")
    if len(trajectory) < 3:
        return None
    extrinsic = sequence.default_gt_extrinsic()
    return round(float(evaluate(sequence.ground_truth(extrinsic), trajectory, gt_extrinsic=extrinsic)[0].ate.rmse), 4)


@dataclass
class LiveStack:
    """A running stack as a live session's clients reach it: the gateway (URL, headers, CA to verify), how an
    observer joins the bus, and how ``twohr camera`` joins it (``--zenoh-config`` or a robot's ``--keys``)."""

    system: object
    url: str
    observer: object  # twohr.bus.BusConfig
    camera_args: list[str]
    headers: dict = field(default_factory=dict)
    verify: object = True  # an ssl.SSLContext with the fleet CA, over HTTPS
    edge: bool = False  # the robot tracks itself (twohr camera --edge): its frames never reach the stack

    def http(self):
        import httpx

        return httpx.Client(base_url=self.url, timeout=60, headers=self.headers, verify=self.verify)


class _CameraSession:
    """One camera session's state as :func:`camera_session` runs it: the cameras it starts, the poses it hears,
    the RSS samples and upstream bytes it counts, and what the gateway says of the session at its end."""

    def __init__(self, stack: LiveStack, sequence, robot: str, frames: int, camera_runs: int, start: int,
                 rate: float, sample_every_s: float, progress: bool, camera_hz: float) -> None:
        self.stack, self.sequence, self.robot, self.frames = stack, sequence, robot, frames
        self.camera_runs, self.start, self.rate, self.camera_hz = camera_runs, start, rate, camera_hz
        self.sample_every_s, self.progress = sample_every_s, progress
        self.per_run = frames // camera_runs
        self.poses = PoseLog()
        self.rss: dict[str, list[tuple[float, float]]] = {}
        self.upstream: list[tuple[int, float]] = []  # (bytes, seconds) each camera run sent
        self.edge_camera: subprocess.Popen | None = None
        self.session_id = ""
        self.info: dict = {}
        self.served = self.online = None

    def start_camera(self) -> subprocess.Popen:
        return subprocess.Popen(
            [sys.executable, "-m", "twohr_app", "camera", "--replay", str(self.sequence.root), "--rate",
             f"{self.camera_hz:g}",
             "--robot", self.robot, *self.stack.camera_args, "--frames", str(self.per_run), "--start",
             str(self.start), *(["--loop"] if self.per_run > len(self.sequence) else []),
             *(["--edge"] if self.stack.edge else [])],
            stdout=subprocess.PIPE, text=True)

    def post(self, client, config_overrides: dict | None, map_request: dict | None,
             posted: threading.Event | None, post_after: threading.Event | None) -> None:
        """Start the robot's own tracker (with ``--edge``), then the session, once ``post_after`` is set."""
        if self.stack.edge:
            self.edge_camera = self.start_camera()
            if "tracks itself" not in self.edge_camera.stdout.readline():
                raise RuntimeError(f"robot {self.robot}'s own tracker did not start")
        if post_after is not None and not post_after.wait(120):
            raise RuntimeError(f"robot {self.robot}: the session it starts after did not start")
        response = client.post("/sessions", json={"source": "camera", "robot_id": self.robot, "record": False,
                                                  "config": config_overrides or {}, "rate": self.rate,
                                                  **({"map": map_request} if map_request else {})})
        response.raise_for_status()
        self.session_id = response.json()["id"]
        if posted is not None:
            posted.set()

    def _running(self, client, camera: subprocess.Popen) -> bool:
        if camera is not self.edge_camera:
            return camera.poll() is None
        # a robot's own tracker lingers for the session's stop: its frames are done once all are counted
        return camera.poll() is None and (client.get(f"/sessions/{self.session_id}").json()["frames_sent"] or 0) \
            < self.per_run * self.relayed_share - 1

    @property
    def relayed_share(self) -> float:
        """The share of the camera's frames the source relays: all, or those of the session's admitted rate."""
        return min(1.0, self.rate / self.camera_hz) if self.rate else 1.0

    def feed(self, client) -> None:
        """Run the cameras one after another, sampling every process's RSS every ``sample_every_s``."""
        t0 = time.monotonic()
        next_sample = t0
        for _ in range(self.camera_runs):
            camera = self.edge_camera or self.start_camera()
            while self._running(client, camera):
                if time.monotonic() >= next_sample:
                    self._sample(camera, t0)
                    next_sample += self.sample_every_s
                time.sleep(0.2)
            if camera is not self.edge_camera:
                self.upstream.append(_camera_upstream(camera.stdout.read()))

    def _sample(self, camera: subprocess.Popen, t0: float) -> None:
        for name, pid in [(child.name, child.proc.pid) for child in self.stack.system.group.children] + (
                [("edge tracker", camera.pid)] if camera is self.edge_camera else []):
            value = rss_mib(pid)
            if value is not None:
                self.rss.setdefault(name, []).append((round(time.monotonic() - t0, 1), round(value, 1)))
        if self.progress:
            print(f"  {self.robot}: {len(self.poses.received)} poses after {time.monotonic() - t0:.0f} s",
                  flush=True)

    def finish(self, client) -> None:
        """Wait for the last frames' poses, end the session and download both of its trajectories."""
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            info = client.get(f"/sessions/{self.session_id}").json()
            sent = info["frames_sent"] or 0
            if sent >= self.frames * self.relayed_share - 1 \
                    and info["frames"] + (info["frames_dropped"] or 0) >= sent:
                break
            time.sleep(0.5)
        self.info = client.get(f"/sessions/{self.session_id}").json()
        client.delete(f"/sessions/{self.session_id}")
        self.served = client.get(f"/sessions/{self.session_id}/trajectory")
        self.online = client.get(f"/sessions/{self.session_id}/trajectory", params={"online": True})
        if self.edge_camera is not None:  # it ends once the session's final path is out
            self.upstream.append(_camera_upstream(self.edge_camera.communicate(timeout=120)[0]))

    def close(self) -> None:
        if self.edge_camera is not None and self.edge_camera.poll() is None:
            self.edge_camera.kill()

    def row(self, busy: int) -> dict:
        info, served, online, frames = self.info, self.served, self.online, self.frames
        looped = frames > len(self.sequence) or self.camera_runs > 1
        latency = self.poses.latency_ms()
        relayed = info["frames_sent"] or frames  # fewer than the camera sent where the session was admitted at a rate
        row = {"robot": self.robot, "tracking": "edge" if self.stack.edge else "central", "busy_processes": busy,
               "frames": frames, "relayed": relayed, "posed": info["frames"],
               "dropped": info["frames_dropped"], "posed_percent": round(100 * info["frames"] / max(1, relayed), 1),
               "fps": info["fps"],
               "latency_ms_p50": round(float(np.percentile(latency, 50)), 1) if len(latency) else None,
               "latency_ms_p99": round(float(np.percentile(latency, 99)), 1) if len(latency) else None,
               "health": info.get("health"), "health_detail": info.get("health_detail"),
               "served": served.headers.get("x-twohr-trajectory"),
               "ate_served": None if looped else _score(self.sequence, served.text),
               "ate_online": None if looped else _score(self.sequence, online.text), "rss_mib": self.rss,
               "upstream_bytes_per_s": round(sum(b for b, _ in self.upstream)
                                             / max(1e-9, sum(s for _, s in self.upstream))),
               "session_id": self.session_id, "served_tum": served.text, "frame_id": info.get("frame_id"),
               "merge": info.get("merge")}
        stamps = np.array([r for _, r, _ in self.poses.received])
        if looped and len(stamps) > 1:
            minutes = (stamps - stamps[0]) / 60
            per_minute = np.bincount(minutes.astype(int))
            row["fps_per_minute"] = [round(n / 60, 2) for n in per_minute[:-1]]  # the last minute is partial
        return row


def camera_session(stack: LiveStack, sequence, robot: str, frames: int, busy: int,
                   sample_every_s: float = 10.0, progress: bool = True, camera_runs: int = 1,
                   config_overrides: dict | None = None, start: int = 0, rate: float = 0.0,
                   map_request: dict | None = None, posted: threading.Event | None = None,
                   post_after: threading.Event | None = None, camera_hz: float = 30.0) -> dict:
    """One live camera session with ``busy`` busy processes beside the stack; see the module docstring.
    ``camera_runs`` > 1 feeds the session ``frames`` frames that many times, each by a new ``twohr camera`` (a new
    client on the bus whose stamps start again, as a robot's camera driver restarted); ``frames`` then counts all.
    ``config_overrides`` (dotted keys) is the session's pipeline config, as ``POST /sessions`` takes it. ``start``:
    the sequence's first frame the camera sends; ``rate``: the session's admitted rate (Hz, 0 = the camera's).
    ``map_request``: the session's ``map`` (e.g. ``{"name": "lab", "mode": "share"}``). ``post_after``: the session
    is started once this event is set (another robot's session first), and ``posted`` is set once it was.
    ``camera_hz``: the frame rate the camera sends the recorded frames at."""
    from twohr import keys
    from twohr.bus import open_session

    if stack.edge and camera_runs != 1:
        raise ValueError("a robot that tracks itself runs one camera per session")
    session = _CameraSession(stack, sequence, robot, frames, camera_runs, start, rate, sample_every_s, progress,
                             camera_hz)
    observer = open_session(stack.observer)
    subscriber = observer.declare_subscriber(keys.key(robot, "pose"), session.poses)
    hogs = _busy(busy)
    try:
        with stack.http() as client:
            session.post(client, config_overrides, map_request, posted, post_after)
            session.feed(client)
            session.finish(client)
    finally:
        for hog in hogs:
            hog.kill()
        session.close()
        subscriber.undeclare()
        observer.close()
    return session.row(busy)


def process_cpu_s(system) -> dict[str, float]:
    """CPU seconds (user + system) each of the stack's processes has used so far, by its name."""
    used = {}
    for child in system.group.children:
        try:
            fields = Path(f"/proc/{child.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
            used[child.name] = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        except (OSError, IndexError, ValueError):
            pass
    return used


def _camera_upstream(printed: str) -> tuple[int, float]:
    """(bytes, seconds) a ``twohr camera`` run sent to the stack, from its last line: every frame goes upstream (with
    ``--edge``: the keyframe jobs and the results)."""
    import re

    found = re.search(r"in ([0-9.]+) s \(.*\), ([0-9]+) bytes", printed or "")
    return (int(found[2]), float(found[1])) if found else (0, 0.0)


def _stack_cpu_s(system) -> float:
    """CPU seconds (user + system) the stack's processes have used so far."""
    return sum(process_cpu_s(system).values())


def fleet_runs(sequence, robots: int, frames: int, busy_counts: list[int], repeats: int, progress: bool = True,
               config_overrides: dict | None = None, tls: bool = False, replicas: dict[str, int] | None = None,
               rate: float = 0.0, tracking: tuple[str, ...] = ("central",)) -> list[dict]:
    """``robots`` live robots at once on one stack (``twohr bench --live --robots N``): each its own ``twohr
    camera`` at 30 Hz on its own stretch of the sequence (starts spread over it: frames 0-299 and 260-559 for two
    robots of 300 frames on the 560-frame dev sequence), its own robot id and, with ``tls``, its own bundle. One row
    per robot and run, with the stack's CPU over the run divided among the robots (``stack_cores_per_robot``:
    cores; ``stack_cpu_ms_per_posed_frame``). The stack admits them all (``--max-robots`` = ``robots``)."""
    from concurrent.futures import ThreadPoolExecutor

    from twohr.bus import free_port
    from twohr_app.supervisor import start_system

    router = f"{'tls' if tls else 'tcp'}/127.0.0.1:{free_port()}"
    port = free_port()
    names = [f"r{i + 1}" for i in range(robots)]
    step = (len(sequence) - frames) // (robots - 1) if robots > 1 else 0
    with tempfile.TemporaryDirectory(prefix="twohr-fleet-") as scratch:
        keys = _fleet_keys(Path(scratch), router, names, edge="edge" in tracking) if tls else None
        system = start_system(router, [str(sequence.root.parent)], str(Path(scratch) / "recordings"), "127.0.0.1",
                              port, timeout=300, keys=keys, replicas=replicas,
                              max_robots=float(robots))
        try:
            rows = []
            for busy, repeat, how in [(b, r, t) for b in busy_counts for r in range(repeats) for t in tracking]:
                if progress:
                    print(f"{robots} robots x {frames} frames, {busy} busy process(es), run {repeat + 1}, "
                          f"tracked {'by each robot' if how == 'edge' else 'by the stack'}", flush=True)
                stacks = [_stack(system, Path(scratch), router, port, name, keys, edge=how == "edge")
                          for name in names]
                hogs = _busy(busy)
                cpu0, t0 = _stack_cpu_s(system), time.monotonic()
                try:
                    with ThreadPoolExecutor(robots) as pool:
                        run = list(pool.map(
                            lambda i, stack, busy: camera_session(
                                stack, sequence, names[i], frames, busy, progress=progress,
                                config_overrides=config_overrides, start=min(i * step, len(sequence) - frames),
                                rate=rate), range(robots), stacks, [busy] * robots))
                finally:
                    for hog in hogs:
                        hog.kill()
                cpu_s, wall_s = _stack_cpu_s(system) - cpu0, time.monotonic() - t0
                posed = sum(r["posed"] for r in run)
                for row in run:
                    row |= {"robots": robots, "run": repeat + 1, "link": "tls" if tls else "tcp",
                            "stack_cores_per_robot": round(cpu_s / wall_s / robots, 2),
                            "stack_cpu_ms_per_posed_frame": round(1000 * cpu_s / max(1, posed), 1)}
                rows += run
            return rows
        finally:
            system.stop()


def live_runs(sequence, frames: int, busy_counts: list[int], repeats: int, progress: bool = True,
              camera_runs: int = 1, config_overrides: dict | None = None, tls: bool = False,
              tracking: tuple[str, ...] = ("central",)) -> list[dict]:
    """Start ``twohr up`` once and run :func:`camera_session` ``repeats`` times per busy count (each session with
    ``config_overrides``), tracked each way ``tracking`` names (``central``: by the stack; ``edge``: by the robot,
    ``twohr camera --edge``). With ``tls``, the stack runs on a fleet's keys made for the run (every link mutual
    TLS, the gateway on HTTPS) and each session's robot joins with its own bundle, as ``twohr up --keys`` does."""
    from twohr.bus import free_port
    from twohr_app.supervisor import start_system

    router = f"{'tls' if tls else 'tcp'}/127.0.0.1:{free_port()}"
    port = free_port()
    robots = [f"live{busy}x{repeat}" for busy in busy_counts for repeat in range(repeats)]
    with tempfile.TemporaryDirectory(prefix="twohr-live-") as scratch:
        keys = _fleet_keys(Path(scratch), router, robots, edge="edge" in tracking) if tls else None
        system = start_system(router, [str(sequence.root.parent)], str(Path(scratch) / "recordings"), "127.0.0.1",
                              port, timeout=300, ros2_domain=0, keys=keys)
        try:
            rows = []
            for robot, how in [(robot, how) for robot in robots for how in tracking]:
                busy = int(robot[4:].split("x")[0])
                if progress:
                    print(f"camera session: {frames} frames, {busy} busy process(es), {robot}, "
                          f"{'TLS' if tls else 'TCP'}, tracked {'by the robot' if how == 'edge' else 'by the stack'}",
                          flush=True)
                stack = _stack(system, Path(scratch), router, port, robot, keys, edge=how == "edge")
                rows.append({**camera_session(stack, sequence, robot, frames * camera_runs, busy, progress=progress,
                                              camera_runs=camera_runs, config_overrides=config_overrides),
                             "link": "tls" if tls else "tcp"})
            return rows
        finally:
            system.stop()


def _fleet_keys(scratch: Path, router: str, robots: list[str], edge: bool = False) -> Path:
    """A fleet's keys for one bench run, with a bundle per robot (``<scratch>/<robot>.bundle``; ``edge``: each may
    run its own tracker); the operator's token is ``bench-operator-token``."""
    from twohr_app.fleet import Fleet

    fleet = Fleet(scratch / "keys")
    fleet.init(api_token="bench-operator-token")
    for robot in robots:
        fleet.add(robot, scratch / f"{robot}.bundle", endpoint=router, edge=edge)
    return fleet.folder


def _stack(system, scratch: Path, router: str, port: int, robot: str, keys: Path | None,
           edge: bool = False) -> LiveStack:
    """How robot ``robot`` reaches ``system``: with its bundle on a fleet's keys, else with the client config (with
    ``edge``, tracking itself: a tracker's config on a stack without keys, whose roles are all this host's)."""
    import ssl

    from twohr.bus import BusConfig
    from twohr.identity import load_identity
    from twohr_app.fleet import write_client_config

    if keys is None:
        config = write_client_config(scratch / "C.json5", router, system.credentials)
        own = write_client_config(scratch / "T.json5", router, system.credentials, role="tracker") if edge else config
        return LiveStack(system, f"http://127.0.0.1:{port}", BusConfig(config_file=config),
                         ["--zenoh-config", str(own)], edge=edge)
    bundle = scratch / f"{robot}.bundle"
    identity = load_identity(bundle)
    observer = BusConfig(connect=[router], identity=identity, user=None, password=None, config_file=None)
    return LiveStack(system, f"https://127.0.0.1:{port}", observer, ["--keys", str(bundle)],
                     headers={"Authorization": "Bearer bench-operator-token"},
                     verify=ssl.create_default_context(cafile=str(keys / "ca.crt")), edge=edge)


def robot_summary(rows: list[dict]) -> list[dict]:
    """Each robot of the runs and how it was tracked, its medians over them: frames posed (%) and the bytes per
    second it sent upstream (tracked by the stack: every frame, JPEG and depth PNG; tracking itself: its keyframes'
    colour images and its results)."""
    groups = sorted({(row["robot"], row.get("tracking", "central")) for row in rows})
    summary = []
    for robot, tracking in groups:
        mine = [r for r in rows if r["robot"] == robot and r.get("tracking", "central") == tracking]
        summary.append({"robot": robot, "tracking": tracking,
                        "posed_percent": float(np.median([r["posed_percent"] for r in mine])),
                        "upstream_bytes_per_s": float(np.median([r["upstream_bytes_per_s"] for r in mine]))})
    return summary


def format_table(rows: list[dict]) -> str:
    """The sessions as a Markdown table (with the robot count, robot and stack CPU per robot for fleet runs)."""
    fleet = any("robots" in r for r in rows)
    lines = ["| " + ("robots | robot | " if fleet else "") + "tracking | link | busy | frames | posed % | dropped | "
             "FPS | latency p50 / p99 ms | ATE served | ATE online | upstream MB/s | health |" + (
                 " stack cores per robot |" if fleet else ""),
             "|---" * (12 + 3 * fleet) + "|"]
    for r in rows:
        lines.append((f"| {r['robots']} | {r['robot']} " if fleet else "") +
                     f"| {r.get('tracking', 'central')} | {r.get('link', 'tcp')} | {r['busy_processes']} | "
                     f"{r['frames']} | {r['posed_percent']} | "
                     f"{r['dropped']} | {r['fps']} | "
                     f"{r['latency_ms_p50']} / {r['latency_ms_p99']} | {r['ate_served']} ({r['served']}) | "
                     f"{r['ate_online']} | {r.get('upstream_bytes_per_s', 0) / 1e6:.2f} | "
                     f"{r['health']} {r['health_detail'] or ''} |" +
                     (f" {r['stack_cores_per_robot']} |" if fleet else ""))
    return "\n".join(lines)


def soak_summary(row: dict, minutes: float) -> dict:
    """RSS growth of each service after a warm-up, and the FPS of the first and last window, in a soak of
    ``minutes``: warm-up and windows are a fifth of it, at most 5 minutes (and at least 1 for the windows)."""
    warmup_minutes = min(5.0, minutes / 5)
    window_minutes = max(1, min(5, int(minutes // 5)))
    growth = {}
    for name, samples in row["rss_mib"].items():
        later = [v for t, v in samples if t >= warmup_minutes * 60]
        if len(later) >= 2:
            growth[name] = round(later[-1] - later[0], 1)
    per_minute = row.get("fps_per_minute", [])
    window = int(window_minutes)
    first = float(np.mean(per_minute[:window])) if len(per_minute) >= window else None
    last = float(np.mean(per_minute[-window:])) if len(per_minute) >= 2 * window else None
    return {"rss_growth_after_warmup_mib": growth, "fps_first_window": first, "fps_last_window": last,
            "fps_change_percent": round(100 * (last - first) / first, 1) if first and last else None}
