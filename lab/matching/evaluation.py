"""Matching quality on real RGB-D frame pairs with ground-truth geometry (the paper's Table 3).

* **M.S.** (matching score) at t px: correct matches / keypoints in the shared view, where the shared
  view counts keypoints with depth whose ground-truth projection lands inside the other image
  (mean of both directions).
* **MMA** (mean matching accuracy) at t px: correct matches / verifiable matches.

A match is correct when its reprojection error is at most t px (A->B with A's depth, else B->A with
B's depth); a match where neither keypoint has depth cannot be verified and counts in neither.
Both numbers are averaged over frame pairs, as D2-Net and the HPatches protocol do.

The ground truth of some frame pairs is several pixels off (see
:func:`~twohr_lab.matching.data.keypoint_repeatability`); each pair records that descriptor-free
check, so tables can be given over all pairs and over the pairs that pass it.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import numpy as np
from pydantic import BaseModel

from twohr.features import Matches

from .data import KeypointCache, PairGeometry, keypoint_repeatability, pair_geometry

THRESHOLDS = (1.0, 3.0, 5.0)

MatchFunction = Callable[[np.ndarray, np.ndarray], Matches]


class PairResult(BaseModel):
    """Counts of one matcher on one frame pair."""

    frame_a: int
    frame_b: int
    shared_view: float
    matches: int
    verifiable: int
    correct: dict[str, int]
    seconds: float
    gt_repeatability: float = float("nan")


class MethodSummary(BaseModel):
    """Means over frame pairs of one matcher."""

    method: str
    frame_pairs: int
    matching_score: dict[str, float]
    mma: dict[str, float]
    matches_per_pair: float
    correct_per_pair: dict[str, float]
    ms_per_pair_median: float


def _key(threshold: float) -> str:
    return f"{threshold:g}px"


def pair_result(geometry: PairGeometry, xy_a: np.ndarray, xy_b: np.ndarray, matches: Matches, frame_a: int,
                frame_b: int, seconds: float = 0.0, thresholds: Sequence[float] = THRESHOLDS,
                gt_repeatability: float = float("nan")) -> PairResult:
    """Correct / verifiable match counts of one frame pair at each pixel threshold."""
    errors = geometry.errors(matches.idx_a, matches.idx_b, xy_a, xy_b)
    verifiable = ~np.isnan(errors)
    shared = 0.5 * (int(geometry.in_view_a.sum()) + int(geometry.in_view_b.sum()))
    correct = {_key(t): int(np.count_nonzero(errors[verifiable] <= t)) for t in thresholds}
    return PairResult(frame_a=frame_a, frame_b=frame_b, shared_view=shared, matches=len(matches),
                      verifiable=int(verifiable.sum()), correct=correct, seconds=seconds,
                      gt_repeatability=gt_repeatability)


def summarize(method: str, results: list[PairResult], min_gt_repeatability: float | None = None) -> MethodSummary:
    """Per-pair means of M.S. and MMA (pairs without a verifiable match count 0 toward MMA's mean);
    with ``min_gt_repeatability``, only over the pairs whose ground truth passes that check."""
    if min_gt_repeatability is not None:
        results = [r for r in results if r.gt_repeatability >= min_gt_repeatability]
    keys = list(results[0].correct) if results else [_key(t) for t in THRESHOLDS]
    ms = {k: float(np.mean([r.correct[k] / r.shared_view if r.shared_view else 0.0 for r in results]))
          for k in keys}
    mma = {k: float(np.mean([r.correct[k] / r.verifiable if r.verifiable else 0.0 for r in results])) for k in keys}
    return MethodSummary(
        method=method, frame_pairs=len(results), matching_score=ms, mma=mma,
        matches_per_pair=float(np.mean([r.matches for r in results])) if results else 0.0,
        correct_per_pair={k: float(np.mean([r.correct[k] for r in results])) for k in keys},
        ms_per_pair_median=float(np.median([r.seconds for r in results]) * 1000) if results else float("nan"),
    )


def _pairs_with_poses(cache: KeypointCache, pairs: list[tuple[int, int]], desc: str, progress: bool):
    """(a, b, frame_a, frame_b) for every pair whose two frames have a ground-truth pose; each frame loads once."""
    from tqdm import tqdm

    loaded = {}
    for a, b in tqdm(pairs, desc=desc, unit="pair", disable=not progress):
        for i in (a, b):
            if i not in loaded:
                loaded[i] = cache.load(i)
        if loaded[a].pose is not None and loaded[b].pose is not None:
            yield a, b, loaded[a], loaded[b]


def evaluate_matchers(cache: KeypointCache, pairs: list[tuple[int, int]], matchers: dict[str, MatchFunction],
                      thresholds: Sequence[float] = THRESHOLDS, min_gt_repeatability: float | None = None,
                      progress: bool = True) -> tuple[dict[str, MethodSummary], dict[str, list[PairResult]]]:
    """Run every matcher on every cached frame pair; frame pairs without ground-truth poses are skipped."""
    camera = cache.sequence.camera
    results: dict[str, list[PairResult]] = {name: [] for name in matchers}
    depth_maps = {}
    for a, b, frame_a, frame_b in _pairs_with_poses(cache, pairs, "matching", progress):
        if b not in depth_maps:
            depth_maps[b] = cache.sequence.read(b).depth
        geometry = pair_geometry(frame_a, frame_b, camera.matrix, camera.width, camera.height, depth_maps[b])
        repeatability = keypoint_repeatability(geometry, frame_b.keypoints.xy)
        for name, match in matchers.items():
            start = time.perf_counter()
            matches = match(frame_a.keypoints.descriptors, frame_b.keypoints.descriptors)
            seconds = time.perf_counter() - start
            results[name].append(pair_result(geometry, frame_a.keypoints.xy, frame_b.keypoints.xy, matches, a, b,
                                             seconds, thresholds, repeatability))
    return {name: summarize(name, rows, min_gt_repeatability) for name, rows in results.items()}, results


def threshold_sweep(cache: KeypointCache, pairs: list[tuple[int, int]], matcher, taus: Sequence[float],
                    thresholds: Sequence[float] = THRESHOLDS, progress: bool = True) -> dict[float, MethodSummary]:
    """M.S. and MMA of a :class:`~twohr_services.matcher.core.SiameseMatcher` at every tau in ``taus``.

    Candidates and scores are computed once per frame pair, then thresholded: the same matches as
    ``SiameseMatcher(conf with threshold=tau).match`` for each tau, at a fraction of the cost."""
    from twohr.features import Matches
    from twohr_services.matcher.core import knn_candidates, mutual_best

    camera = cache.sequence.camera
    results: dict[float, list[PairResult]] = {tau: [] for tau in taus}
    for a, b, frame_a, frame_b in _pairs_with_poses(cache, pairs, "tau sweep", progress):
        geometry = pair_geometry(frame_a, frame_b, camera.matrix, camera.width, camera.height)
        desc_a, desc_b = frame_a.keypoints.descriptors, frame_b.keypoints.descriptors
        idx_a, idx_b = knn_candidates(desc_a, desc_b, matcher.conf.candidates)
        scores = matcher.score(desc_a, desc_b, idx_a, idx_b)
        best = mutual_best(idx_a, idx_b, scores)
        for tau in taus:
            keep = best[scores[best] >= tau]
            matches = Matches(idx_a[keep], idx_b[keep], scores[keep])
            results[tau].append(pair_result(geometry, frame_a.keypoints.xy, frame_b.keypoints.xy, matches, a, b,
                                            thresholds=thresholds))
    return {tau: summarize(f"tau={tau:g}", rows) for tau, rows in results.items()}


def format_table(summaries: dict[str, MethodSummary], keys: Sequence[str] | None = None) -> str:
    """The Table 3 layout as Markdown: M.S. and MMA at each threshold (``keys`` like "3px"), matches, time."""
    first = next(iter(summaries.values()))
    keys = list(keys or first.matching_score)
    header = ["method"] + [f"M.S. @{k}" for k in keys] + [f"MMA @{k}" for k in keys] + ["matches/pair", "ms/pair"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for s in summaries.values():
        cells = [s.method] + [f"{s.matching_score[k]:.3f}" for k in keys] + [f"{s.mma[k]:.3f}" for k in keys]
        cells += [f"{s.matches_per_pair:.0f}", f"{s.ms_per_pair_median:.1f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
