"""Detector timings: each network at full and half resolution, the 2HR filter, and the ORB baseline.

Timings on a shared machine are noisy, so every number is a median of several runs and each
network is timed against a baseline in the same loop (interleaved runs): the exported graph
unchanged, with its dense normalised descriptor output. Ratios are the robust numbers.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import numpy as np
from tqdm import tqdm

from twohr.config import DetectorConfig
from twohr_services.detector.classic import ORBDetector
from twohr_services.detector.core import R2D2Detector
from twohr_services.detector.filter import twohr_filter
from twohr_services.detector.images import network_size
from twohr_services.detector.networks import R2D2Network

DEFAULT_MODELS = ("faster2d2_WASF_N16", "r2d2_WASF_N16", "r2d2_WASF_N16_int8")
DEFAULT_SCALES = (1.0, 0.5)


def _median_ms(fn: Callable[[], object], runs: int) -> float:
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1000)


def _interleaved_ms(fns: dict[str, Callable[[], object]], runs: int) -> dict[str, float]:
    """Median ms of each function, run in turn ``runs`` times after one warm-up call each."""
    for fn in fns.values():
        fn()
    times: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(runs):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    return {name: float(np.median(t) * 1000) for name, t in times.items()}


def filter_scores(n: int = 5000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Reliability and repeatability of ``n`` points shaped like real candidates after the 0.7 floors."""
    rng = np.random.default_rng(seed)
    reliability = np.clip(1 - rng.exponential(0.03, n), 0.7, 1)
    repeatability = 0.7 + 0.3 * rng.beta(2, 1.5, n)
    return reliability, repeatability


def benchmark_detector(image: np.ndarray, models: Sequence[str] = DEFAULT_MODELS,
                       scales: Sequence[float] = DEFAULT_SCALES, runs: int = 5, threads: int = 2,
                       filter_points: int = 5000, filter_runs: int = 200, progress: bool = True) -> dict:
    """Median milliseconds per frame on ``image`` (RGB uint8). Returns a JSON-ready dict:

    * ``networks``: per model and scale, the network with sparse descriptors (what the detector
      runs), the unchanged exported graph (baseline) and their ratio, plus the whole ``detect()``;
    * ``filter``: the 2HR filter on ``filter_points`` candidates;
    * ``orb``: OpenCV ORB ``detect()`` on the same image, a classical reference.
    """
    if runs < 1:
        raise ValueError("runs must be at least 1")
    height, width = image.shape[:2]
    result: dict = {"image": [width, height], "runs": runs, "threads": threads, "networks": []}
    jobs = [(m, s) for m in models for s in scales]
    for model, scale in tqdm(jobs, desc="bench networks", disable=not progress):
        size = network_size(width, height, scale)
        sparse = R2D2Network(model, threads)
        dense = R2D2Network(model, threads, sparse_descriptors=False)
        detector = R2D2Detector(DetectorConfig(model=model, input_scale=scale, threads=threads, latency_budget_ms=None))
        times = _interleaved_ms({"sparse": lambda net=sparse, size=size: net(image, size),
                                 "dense": lambda net=dense, size=size: net(image, size),
                                 "detect": lambda det=detector: det.detect(image)}, runs)
        result["networks"].append({
            "model": model, "scale": scale, "input": list(size),
            "network_ms": times["sparse"], "baseline_dense_ms": times["dense"],
            "ratio_to_baseline": times["sparse"] / times["dense"], "detect_ms": times["detect"],
            "keypoints": len(detector.detect(image)),
        })
    reliability, repeatability = filter_scores(filter_points)
    result["filter"] = {"points": filter_points, "runs": filter_runs,
                        "ms": _median_ms(lambda: twohr_filter(reliability, repeatability), filter_runs)}
    orb = ORBDetector()
    result["orb"] = {"ms": _interleaved_ms({"orb": lambda: orb.detect(image)}, runs)["orb"]}
    return result


def markdown_bench(result: dict) -> str:
    """The benchmark as a markdown table."""
    lines = ["| network | input | network ms (sparse desc.) | exported graph ms (baseline) | ratio | detect() ms | "
             "× ORB time | keypoints |", "|---|---|---|---|---|---|---|---|"]
    orb = result["orb"]["ms"]
    for r in result["networks"]:
        lines.append(f"| {r['model']} | {r['input'][0]}×{r['input'][1]} | {r['network_ms']:.0f} | "
                     f"{r['baseline_dense_ms']:.0f} | {r['ratio_to_baseline']:.2f} | {r['detect_ms']:.0f} | "
                     f"{r['detect_ms'] / orb:.0f} | {r['keypoints']} |")
    f = result["filter"]
    lines.append("")
    lines.append(f"2HR filter on {f['points']} points: {f['ms']:.2f} ms (median of {f['runs']}); "
                 f"ORB detect(): {orb:.1f} ms; medians of {result['runs']} interleaved runs, "
                 f"{result['threads']} threads.")
    return "\n".join(lines)
