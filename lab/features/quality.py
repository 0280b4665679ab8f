"""Feature quality on a real RGB-D sequence: the paper's Table 2 and the 2HR parameter study.

Frame pairs ``(a, a + delta)`` start every ``step`` frames; ground-truth camera poses are
interpolated at the colour timestamps (the sequence's default extrinsic, ``bonn`` for Bonn). Each
pair gives %Rep (A->B, see :func:`~.evaluation.repeatability`) and %Prec (mutual nearest-neighbour
matches correct at the threshold, see :func:`~.evaluation.match_precision`); both are averaged over
pairs. Frames are read and detected once, in order, and dropped as soon as no pair needs them.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, Field
from tqdm import tqdm

from twohr.config import DetectorConfig
from twohr.dataset import Frame, RGBDSequence
from twohr.errors import DatasetError
from twohr.features import Keypoints
from twohr_lab.pairs import frame_poses, relative_pose
from twohr_services.detector.core import R2D2Detector, build_detector
from twohr_services.detector.filter import local_maxima, select_keypoints
from twohr_services.detector.images import network_size
from twohr_services.detector.networks import R2D2Network

from .evaluation import clustered_fraction, match_precision, repeatability

#: Table 2 rows: name -> (features, descriptor as printed).
METHODS: dict[str, tuple[str, str]] = {
    "FAST": ("fast", "ORB (256 bit), at FAST corners"),
    "ORB": ("orb", "ORB (256 bit)"),
    "SIFT": ("sift", "SIFT (128 float)"),
    "R2D2": ("r2d2", "R2D2 (128 float)"),
    "2HR": ("2hr", "R2D2 (128 float)"),
}
GRID_CELLS = (16, 12)  # coverage grid: 40x40 px cells on a 640x480 image
#: Displacement (px) of the reprojections for the chance level of %Rep: what keypoint density alone earns.
CHANCE_SHIFT_PX = 10.0


# ----------------------------------------------------------------------------- pairs and geometry


def plan_pairs(num_frames: int, deltas: Sequence[int], step: int, start: int = 0,
               stop: int | None = None) -> list[tuple[int, int]]:
    """Pairs ``(a, a + delta)`` for anchors ``a = start, start + step, ...`` with both frames below ``stop``."""
    stop = num_frames if stop is None else min(stop, num_frames)
    return [(a, a + d) for a in range(start, stop, step) for d in deltas if a + d < stop]


@dataclass
class SequenceGeometry:
    """Intrinsics and interpolated ground-truth camera poses of every frame of a sequence."""

    k: np.ndarray
    poses: np.ndarray
    valid: np.ndarray
    extrinsic: str

    @classmethod
    def of(cls, sequence: RGBDSequence) -> SequenceGeometry:
        poses, valid = frame_poses(sequence)
        return cls(sequence.camera.matrix, poses, valid, sequence.default_gt_extrinsic())

    def t_b_a(self, a: int, b: int) -> np.ndarray:
        return relative_pose(self.poses[a], self.poses[b])


def iterate_pairs(sequence: RGBDSequence, pairs: list[tuple[int, int]], process: Callable[[Frame], object],
                  desc: str = "frames", progress: bool = True) -> Iterator[tuple[int, int, Frame, Frame, object,
                                                                                 object]]:
    """Yield ``(a, b, frame_a, frame_b, result_a, result_b)`` for every pair, with ``result = process(frame)``.

    Every frame is read and processed once, in order; it is released when no later pair needs it.
    """
    needed = sorted({i for pair in pairs for i in pair})
    last_use = {}
    for index, (a, b) in enumerate(pairs):
        last_use[a] = last_use[b] = index
    cache: dict[int, tuple[Frame, object]] = {}
    bar = tqdm(total=len(needed), desc=desc, unit="frame", disable=not progress)
    for index, (a, b) in enumerate(pairs):
        for i in (a, b):
            if i not in cache:
                frame = sequence.read(i)
                cache[i] = (frame, process(frame))
                bar.update(1)
        yield a, b, cache[a][0], cache[b][0], cache[a][1], cache[b][1]
        for i in (a, b):
            if last_use[i] == index:
                del cache[i]
    bar.close()


def coverage(xy: np.ndarray, image_size: tuple[int, int], cells: tuple[int, int] = GRID_CELLS) -> float:
    """Fraction of the cells of a ``cells`` = (columns, rows) grid over the image that hold a keypoint."""
    width, height = image_size
    if len(xy) == 0:
        return 0.0
    col = np.clip((xy[:, 0] + 0.5) * cells[0] / width, 0, cells[0] - 1).astype(int)
    row = np.clip((xy[:, 1] + 0.5) * cells[1] / height, 0, cells[1] - 1).astype(int)
    return len(np.unique(row * cells[0] + col)) / (cells[0] * cells[1])


# ----------------------------------------------------------------------------- per-pair scores


class PairScore(BaseModel):
    """One method on one frame pair."""

    a: int
    b: int
    shared: int = Field(description="keypoints of A in B's view (depth-checked)")
    repeated: int
    repeated_one_to_one: int
    chance_repeated: int = Field(0, description="as repeated, with the reprojections moved CHANCE_SHIFT_PX sideways")
    matches: int = Field(description="mutual nearest-neighbour matches")
    verifiable: int
    correct: int

    @property
    def delta(self) -> int:
        return self.b - self.a


def score_pair(kp_a: Keypoints, kp_b: Keypoints, frame_a: Frame, frame_b: Frame, k: np.ndarray, t_b_a: np.ndarray,
               threshold: float) -> PairScore:
    """%Rep and %Prec counts of one keypoint pair set."""
    size = frame_a.rgb.shape[1::-1]
    rep = repeatability(kp_a.xy, kp_b.xy, frame_a.depth, k, t_b_a, size, frame_b.depth, threshold)
    chance = repeatability(kp_a.xy, kp_b.xy, frame_a.depth, k, t_b_a, size, frame_b.depth, threshold,
                           displacement=(CHANCE_SHIFT_PX, 0.0))
    prec = match_precision(kp_a.xy, kp_a.descriptors, kp_b.xy, kp_b.descriptors, frame_a.depth, frame_b.depth,
                           k, t_b_a, threshold)
    return PairScore(a=frame_a.index, b=frame_b.index, shared=rep.shared, repeated=rep.repeated,
                     repeated_one_to_one=rep.repeated_one_to_one, chance_repeated=chance.repeated,
                     matches=prec.matches, verifiable=prec.verifiable, correct=prec.correct)


def summarise(scores: list[PairScore], deltas: Sequence[int]) -> dict[str, dict[str, float]]:
    """Per delta: mean %Rep and %Prec over pairs (pairs without shared view or verifiable matches are skipped),
    mean matches and correct matches per pair, and the number of pairs."""
    out: dict[str, dict[str, float]] = {}
    for d in deltas:
        sel = [s for s in scores if s.delta == d]
        rep = [100 * s.repeated / s.shared for s in sel if s.shared]
        rep_1to1 = [100 * s.repeated_one_to_one / s.shared for s in sel if s.shared]
        chance = [100 * s.chance_repeated / s.shared for s in sel if s.shared]
        prec = [100 * s.correct / s.verifiable for s in sel if s.verifiable]
        out[str(d)] = {
            "rep": float(np.mean(rep)) if rep else float("nan"),
            "rep_1to1": float(np.mean(rep_1to1)) if rep_1to1 else float("nan"),
            "rep_chance": float(np.mean(chance)) if chance else float("nan"),
            "prec": float(np.mean(prec)) if prec else float("nan"),
            "matches": float(np.mean([s.matches for s in sel])) if sel else float("nan"),
            "correct": float(np.mean([s.correct for s in sel])) if sel else float("nan"),
            "pairs": len(sel),
        }
    return out


# ----------------------------------------------------------------------------- Table 2


class MethodRow(BaseModel):
    """One row of the feature table."""

    method: str
    descriptor: str
    by_delta: dict[str, dict[str, float]]
    keypoints_per_frame: float
    coverage: float = Field(description=f"fraction of {GRID_CELLS[0]}x{GRID_CELLS[1]} grid cells with a keypoint")
    clustered: float = Field(0.0, description="fraction of keypoints with another keypoint of the same frame "
                             "within the threshold")
    ms_per_frame: float = Field(description="median detection time per frame (network + extraction + filter)")
    pairs: list[PairScore] = Field(default_factory=list, repr=False)


class FeatureTable(BaseModel):
    """The paper's Table 2 on one sequence."""

    sequence: str
    gt_extrinsic: str
    deltas: list[int]
    step: int
    frames: list[int] = Field(description="[first, stop) frame range the pairs come from")
    frames_detected: int
    threshold_px: float
    detector: DetectorConfig
    rows: list[MethodRow]


class _Extractors:
    """Runs the table's methods on a frame; the R2D2 rows share one network pass and each is timed as
    that pass plus its own extraction."""

    def __init__(self, methods: Sequence[str], conf: DetectorConfig) -> None:
        self.methods = list(methods)
        self.conf = conf
        self.classical = {m: build_detector(conf.model_copy(update={"features": METHODS[m][0]}))
                          for m in methods if METHODS[m][0] in ("orb", "fast", "sift")}
        self.r2d2 = {m: R2D2Detector(conf.model_copy(update={"features": METHODS[m][0]}))
                     for m in methods if METHODS[m][0] in ("r2d2", "2hr")}
        self.network = next(iter(self.r2d2.values())).network if self.r2d2 else None

    def __call__(self, frame: Frame) -> dict[str, tuple[Keypoints, float]]:
        out: dict[str, tuple[Keypoints, float]] = {}
        for name, detector in self.classical.items():
            t0 = time.perf_counter()
            kp = detector.detect(frame.rgb)
            out[name] = (kp, (time.perf_counter() - t0) * 1000)
        if self.r2d2:
            height, width = frame.rgb.shape[:2]
            t0 = time.perf_counter()
            maps = self.network(frame.rgb, network_size(width, height, self.conf.input_scale))
            network_ms = (time.perf_counter() - t0) * 1000
            for name, detector in self.r2d2.items():
                t0 = time.perf_counter()
                kp = detector.keypoints_from_maps(maps, (width, height))
                out[name] = (kp, network_ms + (time.perf_counter() - t0) * 1000)
        return out


def feature_table(sequence: RGBDSequence, methods: Sequence[str] = tuple(METHODS), deltas: Sequence[int] = (1, 5, 10),
                  step: int = 10, start: int = 0, stop: int | None = None, threshold: float = 3.0,
                  conf: DetectorConfig | None = None, progress: bool = True) -> FeatureTable:
    """Table 2: %Rep and %Prec per delta, keypoints and milliseconds per frame, for each method."""
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown methods {unknown}; choose from {list(METHODS)}")
    conf = conf or DetectorConfig(latency_budget_ms=None)
    extract = _Extractors(methods, conf)  # first, so that a bad model fails before any work
    geometry = SequenceGeometry.of(sequence)
    pairs = [(a, b) for a, b in plan_pairs(len(sequence), deltas, step, start, stop)
             if geometry.valid[a] and geometry.valid[b]]
    if not pairs:
        raise DatasetError(f"no frame pairs with ground truth in {sequence.root} for deltas {list(deltas)}, "
                           f"frames [{start}, {stop})")
    scores: dict[str, list[PairScore]] = {m: [] for m in methods}
    per_frame: dict[str, dict[int, tuple[int, float, float, float]]] = {m: {} for m in methods}
    for a, b, frame_a, frame_b, res_a, res_b in iterate_pairs(sequence, pairs, extract, "detecting", progress):
        t_b_a = geometry.t_b_a(a, b)
        for m in methods:
            (kp_a, ms_a), (kp_b, ms_b) = res_a[m], res_b[m]
            size = frame_a.rgb.shape[1::-1]
            per_frame[m][a] = (len(kp_a), ms_a, coverage(kp_a.xy, size), clustered_fraction(kp_a.xy, threshold))
            per_frame[m][b] = (len(kp_b), ms_b, coverage(kp_b.xy, size), clustered_fraction(kp_b.xy, threshold))
            scores[m].append(score_pair(kp_a, kp_b, frame_a, frame_b, geometry.k, t_b_a, threshold))
    rows = []
    for m in methods:
        counts, times, covered, clustered = (np.array(v) for v in zip(*per_frame[m].values(), strict=True))
        rows.append(MethodRow(method=m, descriptor=METHODS[m][1], by_delta=summarise(scores[m], deltas),
                              keypoints_per_frame=float(counts.mean()), coverage=float(covered.mean()),
                              clustered=float(clustered.mean()),
                              ms_per_frame=float(np.median(times)), pairs=scores[m]))
    frames_used = sorted({i for pair in pairs for i in pair})
    return FeatureTable(sequence=str(sequence.root), gt_extrinsic=geometry.extrinsic, deltas=list(deltas), step=step,
                        frames=[start, stop if stop is not None else len(sequence)], frames_detected=len(frames_used),
                        threshold_px=threshold, detector=conf, rows=rows)


def markdown_details(table: FeatureTable) -> str:
    """Companion table: one-to-one %Rep, the chance level of %Rep (reprojections moved CHANCE_SHIFT_PX), the share
    of keypoints with a neighbour within the threshold, and matches and correct matches per pair."""
    deltas = table.deltas
    head = (["method"] + [f"%Rep 1:1 Δ{d}" for d in deltas]
            + [f"chance %Rep Δ{deltas[0]}", f"kp with a neighbour ≤ {table.threshold_px:g} px"]
            + [f"matches Δ{d}" for d in deltas] + [f"correct Δ{d}" for d in deltas] + ["pairs"])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in table.rows:
        cells = [r.method] + [f"{r.by_delta[str(d)]['rep_1to1']:.1f}" for d in deltas]
        cells += [f"{r.by_delta[str(deltas[0])]['rep_chance']:.1f}", f"{100 * r.clustered:.0f} %"]
        for key in ("matches", "correct"):
            cells += [f"{r.by_delta[str(d)][key]:.0f}" for d in deltas]
        cells.append("/".join(str(int(r.by_delta[str(d)]["pairs"])) for d in deltas))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def restrict(table: FeatureTable, first_frame: int, stop: int | None = None) -> FeatureTable:
    """The same table summarised over the pairs whose frames lie in ``[first_frame, stop)`` only (timing kept)."""
    stop = stop if stop is not None else 1 << 62
    rows = []
    for row in table.rows:
        kept = [p for p in row.pairs if first_frame <= p.a and p.b < stop]
        rows.append(row.model_copy(update={"pairs": kept, "by_delta": summarise(kept, table.deltas)}))
    return table.model_copy(update={"rows": rows, "frames": [first_frame, min(stop, table.frames[1])]})


def markdown_table(table: FeatureTable, baseline: str = "ORB") -> str:
    """The table as GitHub markdown: one %Rep and one %Prec column per delta."""
    deltas = table.deltas
    base = next((r.ms_per_frame for r in table.rows if r.method == baseline), None)
    head = (["method", "descriptor"] + [f"%Rep Δ{d}" for d in deltas] + [f"%Prec Δ{d}" for d in deltas]
            + ["kp/frame", "coverage", "ms/frame"] + ([f"× {baseline} time"] if base else []))
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in table.rows:
        cells = [r.method, r.descriptor]
        cells += [f"{r.by_delta[str(d)]['rep']:.1f}" for d in deltas]
        cells += [f"{r.by_delta[str(d)]['prec']:.1f}" for d in deltas]
        cells += [f"{r.keypoints_per_frame:.0f}", f"{100 * r.coverage:.0f} %", f"{r.ms_per_frame:.1f}"]
        if base:
            cells.append(f"{r.ms_per_frame / base:.1f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- the 2HR parameter study


@dataclass
class Candidates:
    """All 3x3 maxima of one frame (no score floors) with their scores and unit descriptors, in image pixels."""

    xy: np.ndarray
    reliability: np.ndarray
    repeatability: np.ndarray
    descriptors: np.ndarray

    def keypoints(self, conf: DetectorConfig) -> Keypoints:
        """What :class:`~.core.R2D2Detector` with ``conf`` returns for this frame (same network and scale)."""
        keep = select_keypoints(self.reliability, self.repeatability, conf)
        rel, rep = self.reliability[keep], self.repeatability[keep]
        return Keypoints(self.xy[keep], self.descriptors[keep], rel * rep, rel, rep)


def frame_candidates(network: R2D2Network, rgb: np.ndarray, conf: DetectorConfig) -> Candidates:
    """Every candidate the detector could keep, so that many configurations can be scored from one network pass."""
    height, width = rgb.shape[:2]
    maps = network(rgb, network_size(width, height, conf.input_scale))
    net_h, net_w = maps.repeatability.shape
    border = max(0, int(round(conf.border * net_w / width)))
    ys, xs = local_maxima(maps.repeatability, maps.reliability, 0.0, 0.0, border)
    xy = np.stack([(xs + 0.5) * (width / net_w) - 0.5, (ys + 0.5) * (height / net_h) - 0.5], axis=1)
    return Candidates(xy.astype(np.float32), maps.reliability[ys, xs].copy(), maps.repeatability[ys, xs].copy(),
                      maps.descriptors_at(ys, xs))


#: Parameter -> values studied; each setting changes one parameter of the base configuration.
STUDY_GRID: dict[str, list[float]] = {
    "reliability_clusters": list(range(1, 11)),
    "repeatability_clusters": list(range(1, 11)),
    "score_threshold": [0.0, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9],
    "floors": [0.0, 0.3, 0.5, 0.6, 0.7, 0.8, 0.9],
}


class StudyPoint(BaseModel):
    """One configuration of the study, summarised per delta."""

    parameter: str
    value: float
    by_delta: dict[str, dict[str, float]]
    keypoints_per_frame: float
    coverage: float


class StudyResult(BaseModel):
    sequence: str
    deltas: list[int]
    step: int
    frames: list[int]
    frames_detected: int
    threshold_px: float
    base: DetectorConfig
    raw_r2d2: StudyPoint
    points: list[StudyPoint]


def study_configs(base: DetectorConfig, grid: dict[str, list[float]] = STUDY_GRID) -> list[tuple[str, float,
                                                                                                 DetectorConfig]]:
    """(parameter, value, config) for every studied setting; ``floors`` sets both score floors."""
    out = []
    for parameter, values in grid.items():
        for value in values:
            if parameter == "floors":
                update = {"min_reliability": value, "min_repeatability": value}
            elif parameter.endswith("clusters"):
                update = {parameter: int(value)}
            else:
                update = {parameter: value}
            out.append((parameter, float(value), base.model_copy(update=update | {"features": "2hr"})))
    return out


def kmeans_study(sequence: RGBDSequence, base: DetectorConfig | None = None, deltas: Sequence[int] = (1, 5, 10),
                 step: int = 10, start: int = 0, stop: int | None = None, threshold: float = 3.0,
                 grid: dict[str, list[float]] = STUDY_GRID, progress: bool = True) -> StudyResult:
    """Score every setting of ``grid`` (one parameter changed at a time from ``base``) on the same frame pairs."""
    base = base or DetectorConfig(latency_budget_ms=None)
    network = R2D2Detector(base).network
    geometry = SequenceGeometry.of(sequence)
    pairs = [(a, b) for a, b in plan_pairs(len(sequence), deltas, step, start, stop)
             if geometry.valid[a] and geometry.valid[b]]
    if not pairs:
        raise DatasetError(f"no frame pairs with ground truth in {sequence.root} for frames [{start}, {stop})")
    configs = [("raw R2D2", 0.0, base.model_copy(update={"features": "r2d2"}))] + study_configs(base, grid)
    scores: list[list[PairScore]] = [[] for _ in configs]
    stats: list[dict[int, tuple[int, float]]] = [{} for _ in configs]
    candidates = lambda frame: frame_candidates(network, frame.rgb, base)  # noqa: E731
    for a, b, frame_a, frame_b, cand_a, cand_b in iterate_pairs(sequence, pairs, candidates, "study", progress):
        t_b_a = geometry.t_b_a(a, b)
        size = frame_a.rgb.shape[1::-1]
        for i, (_, _, conf) in enumerate(configs):
            kp_a, kp_b = cand_a.keypoints(conf), cand_b.keypoints(conf)
            stats[i][a] = (len(kp_a), coverage(kp_a.xy, size))
            stats[i][b] = (len(kp_b), coverage(kp_b.xy, size))
            scores[i].append(score_pair(kp_a, kp_b, frame_a, frame_b, geometry.k, t_b_a, threshold))
    points = []
    for (parameter, value, _), pair_scores, frame_stats in zip(configs, scores, stats, strict=True):
        counts, covered = (np.array(v) for v in zip(*frame_stats.values(), strict=True))
        points.append(StudyPoint(parameter=parameter, value=value, by_delta=summarise(pair_scores, deltas),
                                 keypoints_per_frame=float(counts.mean()), coverage=float(covered.mean())))
    return StudyResult(sequence=str(sequence.root), deltas=list(deltas), step=step,
                       frames=[start, stop if stop is not None else len(sequence)],
                       frames_detected=len({i for pair in pairs for i in pair}), threshold_px=threshold, base=base,
                       raw_r2d2=points[0], points=points[1:])
