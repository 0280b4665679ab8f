"""The keyframe networks' latency as the detector runs them (``twohr bench --networks``).

Each registered keyframe network (``detector.model``: r2d2, faster2d2, faster2d2-int8, faster2d2-int8-coarse,
student) runs through the detector's own :class:`R2D2Network` (the sparse-descriptor graph, the configured backend,
1 thread) on a VGA-sized input at each input scale and precision. Runs are interleaved (run i of every network,
then run i + 1 ...) so that load from other processes on a shared machine hits all of them alike; each run is the
mean of ``per_run`` inferences and the table reports the median run, and the ratio to faster2d2 f32 at the same
scale.

``twohr bench --networks [--runs 3] [--out runs/bench/networks]``
"""

from __future__ import annotations

import statistics
import time

import numpy as np

from twohr.models import KEYFRAME_NETWORKS, cpu_has_bf16

REFERENCE = ("faster2d2", "f32")


def network_latency(networks: list[str] | None = None, scales: tuple[float, ...] = (0.75, 0.5),
                    precisions: tuple[str, ...] | None = None, runs: int = 3, per_run: int = 10,
                    backend: str = "auto", image_size: tuple[int, int] = (640, 480), progress: bool = True) -> dict:
    """ms per inference of every ``networks`` x ``precisions`` x ``scales``; see the module docstring."""
    from tqdm import tqdm

    from twohr_services.detector.images import network_size
    from twohr_services.detector.networks import R2D2Network

    networks = networks or list(KEYFRAME_NETWORKS)
    precisions = precisions or (("f32", "bf16") if cpu_has_bf16() else ("f32",))
    rgb = np.random.default_rng(0).integers(0, 255, (image_size[1], image_size[0], 3), dtype=np.uint8)
    jobs = {}
    for name in networks:
        for precision in precisions:
            net = R2D2Network(name, 1, backend=backend, precision=precision)
            for scale in scales:
                size = network_size(*image_size, scale)
                for _ in range(2):
                    net(rgb, size)  # compile and warm up
                jobs[(name, precision, scale)] = (net, size)
    times: dict = {key: [] for key in jobs}
    for _ in tqdm(range(runs), desc="networks", disable=not progress):
        for key, (net, size) in jobs.items():
            start = time.perf_counter()
            for _ in range(per_run):
                net(rgb, size)
            times[key].append((time.perf_counter() - start) * 1000 / per_run)
    rows = []
    for (name, precision, scale), per in times.items():
        reference = times.get((*REFERENCE, scale))
        median = statistics.median(per)
        rows.append({"network": name, "model": KEYFRAME_NETWORKS.get(name, name), "precision": precision,
                     "input_scale": scale, "size": list(jobs[(name, precision, scale)][1]), "median_ms": median,
                     "runs_ms": per, "ratio_to_faster2d2_f32": median / statistics.median(reference)
                     if reference else None})
    return {"backend": backend, "threads": 1, "runs": runs, "per_run": per_run, "rows": rows}


def format_table(result: dict) -> str:
    lines = ["| network | precision | input scale | size | median ms | × faster2d2 f32 |", "|---|---|---|---|---|---|"]
    for r in result["rows"]:
        ratio = "" if r["ratio_to_faster2d2_f32"] is None else f"{r['ratio_to_faster2d2_f32']:.2f}"
        lines.append(f"| {r['network']} | {r['precision']} | {r['input_scale']} | {r['size'][0]}x{r['size'][1]} | "
                     f"{r['median_ms']:.1f} | {ratio} |")
    return "\n".join(lines)
