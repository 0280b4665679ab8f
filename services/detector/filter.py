"""The paper's 2HR filter (§3.1) and the keypoint selection around it, on score maps and arrays: the candidates
(3x3 local maxima of repeatability above the score floors), 1-D K-means, the 2HR cluster filter, the top-N cut and
the sub-pixel refinement of the kept peaks. Pure functions of NumPy arrays; no network."""

from __future__ import annotations

from bisect import bisect_right

import cv2
import numpy as np

from twohr.config import DetectorConfig


def kmeans_1d(values: np.ndarray, k: int, iterations: int = 300) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic 1-D K-means. Returns ``(labels, centres)``, centres ascending, so the top cluster is ``k-1``.

    In 1-D every cluster is an interval of the sorted values, so one Lloyd step is k binary searches
    and k differences of prefix sums: O(k log n), done on Python scalars because k is tiny. Two starts
    (centres at quantiles, centres evenly spread over the range) are run to convergence and the one
    with the lower sum of squared errors wins. Clusters may end up empty when there are fewer distinct
    values than ``k``.
    """
    values = np.asarray(values, dtype=np.float64).ravel()
    n = values.size
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    k = max(1, min(int(k), n))
    ordered = np.sort(values)
    sorted_list = ordered.tolist()
    prefix = [0.0, *np.cumsum(ordered).tolist()]
    prefix_sq = [0.0, *np.cumsum(ordered * ordered).tolist()]
    low, high = sorted_list[0], sorted_list[-1]
    starts = [
        [sorted_list[min(n - 1, int((i + 0.5) * n / k))] for i in range(k)],
        [low + (high - low) * (i + 1) / (k + 1) for i in range(k)],
    ]
    best_sse, best_centres = np.inf, sorted(starts[0])
    for centres in starts:
        centres = sorted(centres)
        edges: list[int] = []
        for _ in range(iterations):
            # values <= a midpoint go to the lower cluster
            midpoints = [(a + b) / 2 for a, b in zip(centres, centres[1:], strict=False)]
            new_edges = [0, *(bisect_right(sorted_list, m) for m in midpoints), n]
            if new_edges == edges:
                break
            edges = new_edges
            centres = sorted((prefix[e1] - prefix[e0]) / (e1 - e0) if e1 > e0 else c
                             for e0, e1, c in zip(edges, edges[1:], centres, strict=False))
        sse = sum(prefix_sq[e1] - prefix_sq[e0] - (prefix[e1] - prefix[e0]) ** 2 / (e1 - e0)
                  for e0, e1 in zip(edges, edges[1:], strict=False) if e1 > e0)
        if sse < best_sse - 1e-12:
            best_sse, best_centres = sse, centres
    centres_array = np.array(best_centres)
    labels = np.searchsorted((centres_array[1:] + centres_array[:-1]) / 2, values, side="left")
    return labels.astype(np.int64), centres_array


def twohr_filter(reliability: np.ndarray, repeatability: np.ndarray, reliability_clusters: int = 3,
                 repeatability_clusters: int = 2, score_threshold: float = 0.5) -> np.ndarray:
    """The paper's 2HR selection: boolean mask of points in the top reliability cluster AND the top
    repeatability cluster whose composite score ``reliability * repeatability`` exceeds the threshold.

    The top cluster is the non-empty cluster with the highest centre.
    """
    reliability = np.asarray(reliability, dtype=np.float64).ravel()
    repeatability = np.asarray(repeatability, dtype=np.float64).ravel()
    if reliability.shape != repeatability.shape:
        raise ValueError(f"reliability and repeatability differ in length: {reliability.size} vs {repeatability.size}")
    if reliability.size == 0:
        return np.zeros(0, bool)
    rel_labels, _ = kmeans_1d(reliability, reliability_clusters)
    rep_labels, _ = kmeans_1d(repeatability, repeatability_clusters)
    top_rel = rel_labels == rel_labels.max()
    top_rep = rep_labels == rep_labels.max()
    return top_rel & top_rep & (reliability * repeatability > score_threshold)


def local_maxima(repeatability: np.ndarray, reliability: np.ndarray, min_repeatability: float,
                 min_reliability: float, border: int) -> tuple[np.ndarray, np.ndarray]:
    """(ys, xs) of 3x3 local maxima of repeatability that pass both score floors, away from the border."""
    dilated = cv2.dilate(repeatability, np.ones((3, 3), np.uint8))
    peak = (repeatability == dilated) & (repeatability >= min_repeatability) & (reliability >= min_reliability)
    if border > 0:
        peak[:border] = peak[-border:] = False
        peak[:, :border] = peak[:, -border:] = False
    return np.nonzero(peak)


def subpixel_offsets(score: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel offsets (dy, dx) in [-0.5, 0.5] of peaks (ys, xs) of ``score``: the vertex of a parabola through
    the peak and its two neighbours, per axis. Peaks on the map's border keep offset 0 on that axis."""
    height, width = score.shape
    offsets = []
    for axis, (index, size) in enumerate(((ys, height), (xs, width))):
        inner = (index > 0) & (index < size - 1)
        lo, hi = np.where(inner, index - 1, index), np.where(inner, index + 1, index)
        before = score[lo, xs] if axis == 0 else score[ys, lo]
        after = score[hi, xs] if axis == 0 else score[ys, hi]
        centre = score[ys, xs]
        curvature = before.astype(np.float64) - 2 * centre + after
        # a true maximum curves down; a flat or inverted neighbourhood says nothing below a pixel
        safe = inner & (curvature < -1e-9)
        offset = np.where(safe, 0.5 * (before - after) / np.where(safe, curvature, -1.0), 0.0)
        offsets.append(np.clip(offset, -0.5, 0.5))
    return offsets[0], offsets[1]


def select_keypoints(reliability: np.ndarray, repeatability: np.ndarray, conf: DetectorConfig) -> np.ndarray:
    """Indices of the candidates (already local maxima) that ``conf`` keeps, best composite score first.

    Applies the score floors, the 2HR filter when ``conf.features == "2hr"`` and the top-N cut.
    """
    floors = (reliability >= conf.min_reliability) & (repeatability >= conf.min_repeatability)
    index = np.flatnonzero(floors)
    if conf.features == "2hr" and index.size:
        keep = twohr_filter(reliability[index], repeatability[index], conf.reliability_clusters,
                            conf.repeatability_clusters, conf.score_threshold)
        index = index[keep]
    scores = reliability[index] * repeatability[index]
    return index[np.argsort(-scores, kind="stable")[: conf.max_keypoints]]
