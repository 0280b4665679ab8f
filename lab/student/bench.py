"""Latency of the keyframe networks at 480x360, onnxruntime, 1 thread, median of 5 runs of 20 inferences.

Each network is timed twice: the dense ONNX as exported, and the graph the detector actually runs
(``_prepare_model(..., sparse_descriptors=True)``: the dense descriptor normalisation, and for stride-2
networks the 128-channel upsample, cut off).

``python -m twohr_lab.student.bench --student runs/student/run1/student.onnx``
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

from .int8 import SIZE, TEACHER, cpu_model, session


def bench(models: dict[str, Path], size: tuple[int, int] = SIZE, runs: int = 5, per_run: int = 20) -> dict:
    """ms per inference of every network in both forms; the runs are interleaved (run i of every network,
    then run i + 1 ...) so that load from other processes on a shared machine hits all of them alike."""
    from twohr_services.detector.core import _prepare_model

    sessions = {}
    for name, path in models.items():
        if Path(path).exists():
            sessions[(name, "dense")] = session(Path(path))
            sessions[(name, "detector_sparse")] = session(_prepare_model(str(path), True).model)
    x = np.random.default_rng(0).standard_normal((1, 3, size[1], size[0])).astype(np.float32)
    times: dict = {key: [] for key in sessions}
    for sess in sessions.values():
        for _ in range(3):
            sess.run(None, {"image": x})
    for _ in range(runs):
        for key, sess in sessions.items():
            start = time.perf_counter()
            for _ in range(per_run):
                sess.run(None, {"image": x})
            times[key].append((time.perf_counter() - start) * 1000 / per_run)
    result: dict = {"cpu": cpu_model(), "size": list(size), "threads": 1, "runs": runs, "per_run": per_run}
    for (name, form), per in times.items():
        result.setdefault(name, {})[form] = {"median_ms": statistics.median(per), "min_ms": min(per),
                                             "max_ms": max(per), "runs_ms": per}
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m twohr_lab.student.bench", description=__doc__.split("\n")[0])
    parser.add_argument("--student", default="runs/student/run1/student.onnx")
    parser.add_argument("--int8", default="runs/student/faster2d2_WASF_N16_int8_heads_f32.onnx")
    parser.add_argument("--out", default="runs/student/latency.json")
    args = parser.parse_args(argv)
    result = bench({"faster2d2_f32": TEACHER, "faster2d2_int8_heads_f32": Path(args.int8),
                    "student_f32": Path(args.student)})
    Path(args.out).write_text(json.dumps(result, indent=1))
    print(json.dumps({k: ({m: round(v[m]["median_ms"], 1) for m in v} if isinstance(v, dict) else v)
                      for k, v in result.items()}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
