"""``--max-robots auto``: how many robots this host's stack carries at camera rate, measured, not assumed.

One robot asks of the stack, per second of camera time, :data:`KEYFRAME_JOBS_PER_S` keyframe jobs (detector, yolo,
matcher) and :data:`~twohr_services.gateway.admission.NOMINAL_HZ` tracked frames (optical flow and pose). The first
``twohr up --max-robots auto`` on a host times one of each on rendered 640x480 frames with the default config, in a
child process (the networks' memory goes with it), and keeps the figure per CPU model and core count in
``$XDG_CACHE_HOME/twohr/capacity.json``. ``twohr bench --fleet N`` keeps there the robots its replay carried where it
found a limit (fewer than N), and that figure, measured with many robots' keyframe jobs at once, is taken before the
start-time estimate. The times are wall-clock (the networks run two threads each): ``USABLE_SHARE`` was set against
the 2-core live bench, and the formula is not measured beyond 2 cores. This is the one meaning of ``auto``: the
gateway run alone (compose) has no networks to time and refuses it in one line (give it the figure printed by
``python -m twohr_app.capacity``).

    robots = floor(2 * cores * USABLE_SHARE / (KEYFRAME_JOBS_PER_S * keyframe_s + NOMINAL_HZ * frame_s)) / 2

at least 1 (a stack that cannot carry one robot at 30 Hz still serves one, degraded)."""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from pydantic import BaseModel, Field

from twohr.files import write_atomic

#: keyframe jobs one robot asks for per second at 30 Hz with the default keyframe policy: `twohr bench --fleet 4
#: --frames 300` recorded 33 jobs over 10 s of the dev frames (docs/fleet.md, "Capacity")
KEYFRAME_JOBS_PER_S = 3.3
#: the share of the cores the trackers and networks may count on: the router, gateway, source and recorder and the
#: mapping work beside the networks take the rest (two live robots on 2 cores used 1.52-1.62 stack cores and got
#: 34-60 % of their frames posed: docs/fleet.md)
USABLE_SHARE = 0.6
#: the most robots a kept figure may admit (a cache file edited to 1e6 would start a million trackers; Infinity
#: would stop twohr up): a kept figure out of 1..MAX_ROBOTS is ignored and measured again
MAX_ROBOTS = 256
#: how long the timing run may take (s): the networks are compiled in it
MEASURE_TIMEOUT_S = 300
#: frames of the timing run (its first keyframe job and frame warm the networks and the flow and are not counted)
TIMED_FRAMES = 30


class Capacity(BaseModel):
    """What one host carries, and how that was found."""

    robots: float = Field(ge=1, le=MAX_ROBOTS, description="robots admitted at 30 Hz (--max-robots)")
    cpu_model: str
    cores: int
    keyframe_ms: float | None = Field(None, description="one keyframe job (detector, yolo, matcher, mapping), "
                                      "wall-clock median")
    frame_ms: float | None = Field(None, description="one tracked frame, wall-clock median")
    source: str = Field(description="'measured at start' or 'twohr bench --fleet'")
    measured_at: float = Field(default_factory=time.time)

    def line(self) -> str:
        how = (f"keyframe job {self.keyframe_ms:.0f} ms, frame {self.frame_ms:.1f} ms"
               if self.keyframe_ms is not None else "its replayed keyframe jobs")
        return (f"{self.robots:g} robot{'' if self.robots == 1 else 's'} at 30 Hz on {self.cores} cores of "
                f"{self.cpu_model} ({self.source}: {how})")


def robots_for(cores: int, keyframe_s: float, frame_s: float) -> float:
    """The formula of the module docstring."""
    from twohr_services.gateway.admission import NOMINAL_HZ

    per_robot = KEYFRAME_JOBS_PER_S * keyframe_s + NOMINAL_HZ * frame_s
    return max(1.0, math.floor(2 * cores * USABLE_SHARE / per_robot) / 2)


def _host() -> tuple[str, int]:
    from twohr.machine import machine

    return str(machine()["cpu_model"]), len(os.sched_getaffinity(0))


def cache_file() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "twohr" / "capacity.json"


def _kept() -> dict[str, dict]:
    try:
        return json.loads(cache_file().read_text())
    except (OSError, ValueError):
        return {}


def keep(capacity: Capacity) -> None:
    """Keep ``capacity`` for its host (a bench's figure beside the start-time one)."""
    kept = _kept()
    kept[f"{capacity.cpu_model}|{capacity.cores}|{capacity.source}"] = capacity.model_dump()
    write_atomic(cache_file(), json.dumps(kept, indent=1))  # private: whoever may write it sets the admission


def keep_bench(max_robots: int) -> Capacity:
    """Keep what ``twohr bench --fleet`` found this host carries (at least 1, as the formula)."""
    model, cores = _host()
    capacity = Capacity(robots=float(max(1, max_robots)), cpu_model=model, cores=cores, source="twohr bench --fleet")
    keep(capacity)
    return capacity


def kept_capacity() -> Capacity | None:
    """This host's kept figure: the bench's where there is one, else the start-time one; None when neither is."""
    model, cores = _host()
    kept = _kept()
    for source in ("twohr bench --fleet", "measured at start"):
        found = kept.get(f"{model}|{cores}|{source}")
        if found is not None:
            try:
                return Capacity.model_validate(found)
            except ValueError:
                continue
    return None


def measure() -> Capacity:
    """Run the default schedule in this process on rendered frames, as ``twohr run`` does, and take the median
    keyframe job (every stage and the mapping after them) and the median tracked frame."""
    from twohr.config import PipelineConfig
    from twohr.dataset import Frame
    from twohr.synthetic import SyntheticScene, SyntheticSpec, camera_path
    from twohr_app.pipeline import local_stages
    from twohr_services.tracker.schedule import build_schedule

    spec = SyntheticSpec(frames=TIMED_FRAMES, width=640, height=480)
    scene, path, camera = SyntheticScene(spec), camera_path(spec), spec.camera
    config = PipelineConfig()
    schedule = build_schedule(config, camera, local_stages(config, camera))
    frame_ms = []
    try:
        for index, (stamp, pose) in enumerate(zip(path.stamps, path.poses, strict=True)):
            rgb, depth, _ = scene.render(pose, stamp - spec.start_stamp)
            _, stats = schedule.process(Frame(index, float(stamp), rgb, depth.astype(np.float32)))
            frame_ms.append(stats.ms_tracker)
        schedule.finish()
        jobs = [job.ms_job for job in schedule.keyframe_log if job.kind == "2hr"]
    finally:
        schedule.close()
    if len(jobs) < 2:
        raise RuntimeError(f"the timing run made {len(jobs)} keyframe jobs; it needs 2")
    keyframe, per_frame = float(np.median(jobs[1:])), float(np.median(frame_ms[1:]))
    model, cores = _host()
    return Capacity(robots=robots_for(cores, keyframe / 1000, per_frame / 1000), cpu_model=model, cores=cores,
                    keyframe_ms=round(keyframe, 1), frame_ms=round(per_frame, 2), source="measured at start")


def auto_capacity(say=print) -> Capacity:
    """``--max-robots auto``: the kept figure, else measured now in a child process (a few seconds, once per host)
    and kept."""
    kept = kept_capacity()
    if kept is not None:
        return kept
    say("measuring what this host carries (once per CPU: one keyframe job and one frame, a few seconds) …")
    from twohr.errors import TwohrError

    try:
        done = subprocess.run([sys.executable, "-m", "twohr_app.capacity", "--measure"], capture_output=True,
                              text=True, timeout=MEASURE_TIMEOUT_S)
        if done.returncode != 0:
            raise ValueError((done.stderr.strip().splitlines() or ["no output"])[-1])
        capacity = Capacity.model_validate_json((done.stdout.strip().splitlines() or ["{}"])[-1])
    except (subprocess.TimeoutExpired, ValueError) as exc:
        raise TwohrError(f"--max-robots auto: the measurement failed ({str(exc).splitlines()[0]}); give "
                         "--max-robots N") from None
    keep(capacity)
    return capacity


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m twohr_app.capacity", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--measure", action="store_true", help="measure now (not the kept figure) and print it as "
                        "JSON, keeping nothing")
    args = parser.parse_args(argv)
    if args.measure:
        print(measure().model_dump_json())
    else:
        print(auto_capacity(say=lambda line: print(line, file=sys.stderr)).line())
    return 0


if __name__ == "__main__":
    sys.exit(main())
