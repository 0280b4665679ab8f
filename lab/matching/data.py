"""Real RGB-D frame pairs for the matcher: cached keypoints, ground-truth geometry and pair labels.

Numpy only (no torch, no detector import): the caller passes a detector object with a
``detect(rgb) -> Keypoints`` method, built from the :class:`~twohr.config.DetectorConfig` that also
keys the cache. Used by training (positive/negative pairs) and by evaluation (M.S., MMA).

Geometry: a keypoint ``a`` of frame A with depth ``d`` is back-projected, moved into camera B with
``T_b_a = inv(T_w_b) @ T_w_a`` (camera-to-world ground-truth poses) and projected. Ground truth
assumes a static world, so points on moving people get wrong labels; :func:`label_pairs` therefore
uses only anchors whose projection into B is confirmed by B's depth map (see its docstring).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
from pydantic import BaseModel, Field

from twohr.config import DetectorConfig
from twohr.dataset import RGBDSequence
from twohr.errors import DatasetError
from twohr.features import Keypoints, descriptor_distances
from twohr.files import AS_OPEN, replacing
from twohr.geometry import depth_at_pixels, invert_pose
from twohr_lab.pairs import depth_agrees, frame_poses, in_image, project_into, relative_pose

#: Depth readings outside this range (metres) are treated as missing.


class Detector(Protocol):
    def detect(self, rgb: np.ndarray) -> Keypoints: ...


# ----------------------------------------------------------------------------- keypoint cache


@dataclass
class CachedFrame:
    """Keypoints of one frame with their depth (metres, NaN = none) and ground-truth camera pose."""

    index: int
    stamp: float
    keypoints: Keypoints
    depth_at_keypoints: np.ndarray
    pose: np.ndarray | None


class KeypointCache:
    """Detector output per frame, stored once as ``<root>/<sequence>-<config hash>/<index>.npz``.

    The detector runs at ~0.3-2 s per 640x480 frame on 2 shared cores, so training and evaluation
    read keypoints from here. The folder name hashes the full :class:`DetectorConfig`, so a changed
    detector default never reuses stale keypoints. Descriptors are stored as float16 (halves the
    size; R2D2 descriptors lose < 1e-3 in cosine).
    """

    def __init__(self, sequence: RGBDSequence, detector_conf: DetectorConfig, root: str | Path) -> None:
        self.sequence = sequence
        self.detector_conf = detector_conf
        key = hashlib.sha256(detector_conf.model_dump_json().encode()).hexdigest()[:10]
        self.folder = Path(root) / f"{sequence.name}-{key}"
        self.poses, self.pose_valid = frame_poses(sequence)

    def path(self, index: int) -> Path:
        return self.folder / f"{index:06d}.npz"

    def missing(self, indices: Iterable[int]) -> list[int]:
        return [i for i in indices if not self.path(i).is_file()]

    def fill(self, indices: Iterable[int], detector: Detector, progress: bool = True) -> None:
        """Run ``detector`` on every listed frame that is not cached yet."""
        from tqdm import tqdm

        todo = self.missing(indices)
        if not todo:
            return
        self.folder.mkdir(parents=True, exist_ok=True)
        (self.folder / "detector.json").write_text(
            json.dumps({"sequence": str(self.sequence.root), "detector": self.detector_conf.model_dump()}, indent=2))
        for index in tqdm(todo, desc="keypoints", unit="frame", disable=not progress):
            frame = self.sequence.read(index)
            kp = detector.detect(frame.rgb)
            with replacing(self.path(index), AS_OPEN) as out:
                np.savez(out, xy=kp.xy.astype(np.float32), descriptors=kp.descriptors.astype(np.float16),
                         scores=kp.scores.astype(np.float32),
                         depth=depth_at_pixels(frame.depth, kp.xy).astype(np.float32))

    def load(self, index: int) -> CachedFrame:
        path = self.path(index)
        if not path.is_file():
            raise DatasetError(f"frame {index} is not in the keypoint cache {self.folder}; fill it first")
        with np.load(path) as data:
            kp = Keypoints(data["xy"], data["descriptors"].astype(np.float32), data["scores"])
            depth = data["depth"]
        pose = self.poses[index] if self.pose_valid[index] else None
        return CachedFrame(index, float(self.sequence.stamps[index]), kp, depth, pose)


# ----------------------------------------------------------------------------- pair geometry

#: Visibility of a keypoint of A in frame B (``PairGeometry.visibility_a``).
OUT_OF_VIEW, VISIBLE, OCCLUDED, MOVED = 0, 1, 2, 3


@dataclass
class PairGeometry:
    """Where the keypoints of A land in B (and B's in A) under ground truth.

    ``xy_ab`` (Na, 2) projections of A's keypoints into B (NaN without depth) at depth ``z_ab``,
    ``in_view_a`` (Na,) those that land inside B's image; likewise ``xy_ba`` / ``in_view_b``.
    ``visibility_a`` (Na,), only when B's depth map is given, compares B's depth at the projection with
    the projected depth: VISIBLE (they agree within ``depth_tolerance``), OCCLUDED (B sees something
    nearer by more than 3x the tolerance: the point is hidden),
    MOVED (B sees something farther, or nothing: under a static world that is impossible, so the point
    moved, or its depth in A was unreliable), OUT_OF_VIEW (no depth in A, or outside B's image).
    """

    xy_ab: np.ndarray
    z_ab: np.ndarray
    in_view_a: np.ndarray
    xy_ba: np.ndarray
    in_view_b: np.ndarray
    visibility_a: np.ndarray | None = None

    def errors(self, idx_a: np.ndarray, idx_b: np.ndarray, xy_a: np.ndarray, xy_b: np.ndarray) -> np.ndarray:
        """Reprojection error (px) of each match: A->B where A has depth, else B->A; NaN when neither has depth."""
        err_ab = np.linalg.norm(self.xy_ab[idx_a] - xy_b[idx_b], axis=1)
        err_ba = np.linalg.norm(self.xy_ba[idx_b] - xy_a[idx_a], axis=1)
        return np.where(np.isnan(err_ab), err_ba, err_ab)


def pair_geometry(frame_a: CachedFrame, frame_b: CachedFrame, camera_matrix: np.ndarray, width: int, height: int,
                  depth_map_b: np.ndarray | None = None, depth_tolerance: float = 0.05) -> PairGeometry:
    """Project both keypoint sets into the other frame with the ground-truth relative pose."""
    if frame_a.pose is None or frame_b.pose is None:
        raise DatasetError(f"frames {frame_a.index} and {frame_b.index} need ground-truth poses")
    t_b_a = relative_pose(frame_a.pose, frame_b.pose)
    xy_ab, z_ab = project_into(frame_a.keypoints.xy, frame_a.depth_at_keypoints, camera_matrix, t_b_a)
    xy_ba, z_ba = project_into(frame_b.keypoints.xy, frame_b.depth_at_keypoints, camera_matrix, invert_pose(t_b_a))
    in_a, in_b = in_image(xy_ab, z_ab, width, height), in_image(xy_ba, z_ba, width, height)
    visibility = None
    if depth_map_b is not None:
        measured = depth_at_pixels(depth_map_b, xy_ab).astype(np.float32)
        visibility = np.full(len(xy_ab), OUT_OF_VIEW, np.int8)
        with np.errstate(invalid="ignore"):
            visibility[in_a] = MOVED
            # a clear margin, so depth noise at object edges does not pass for an occlusion
            visibility[in_a & (measured < z_ab * (1 - 3 * depth_tolerance))] = OCCLUDED
        visibility[in_a & depth_agrees(z_ab, measured, depth_tolerance)] = VISIBLE
    return PairGeometry(xy_ab, z_ab, in_a, xy_ba, in_b, visibility)


def keypoint_repeatability(geometry: PairGeometry, xy_b: np.ndarray, px: float = 3.0) -> float:
    """Fraction of A's keypoints, VISIBLE in B (or merely in view without B's depth map), that have a keypoint
    of B within ``px`` of their ground-truth projection.

    It uses no descriptor, so it checks the ground truth independently of any matcher: on this data it
    tracks mutual-NN precision with correlation 0.99 per frame pair, and collapses (< 0.3 where ~0.6 is
    normal) on the pairs whose ground-truth pose is several pixels off.
    """
    usable = geometry.in_view_a if geometry.visibility_a is None else geometry.visibility_a == VISIBLE
    if not usable.any() or len(xy_b) == 0:
        return 0.0
    projected = geometry.xy_ab[usable]
    nearest = np.full(len(projected), np.inf)
    for start in range(0, len(projected), 512):  # bounded memory for large keypoint sets
        chunk = projected[start:start + 512]
        nearest[start:start + 512] = np.linalg.norm(chunk[:, None] - xy_b[None], axis=2).min(1)
    return float(np.mean(nearest <= px))


# ----------------------------------------------------------------------------- training labels


class LabelConfig(BaseModel):
    """How training pairs are labelled from ground-truth geometry (issue #5)."""

    positive_px: float = Field(3.0, gt=0, description="positive: reprojection within this many pixels, both ways")
    negative_px: float = Field(8.0, gt=0, description="negative: farther than this from the projection")
    depth_tolerance: float = Field(0.05, gt=0, description="relative depth agreement for positives and visibility")
    hard_negatives: int = Field(4, ge=0, description="descriptor nearest neighbours per anchor used as negatives")
    random_negatives: int = Field(1, ge=0, description="random far keypoints per anchor used as negatives")
    max_anchors: int = Field(100, ge=1, description="anchors sampled per frame pair")
    occluded_anchors: bool = Field(True, description="occluded anchors give negatives (their match is hidden)")
    min_pair_repeatability: float = Field(
        0.35, ge=0, le=1, description="skip frame pairs whose ground truth fails the keypoint_repeatability check")


#: ``LabelledPairs.kind`` codes.
POSITIVE, HARD_NEGATIVE, RANDOM_NEGATIVE = 0, 1, 2


@dataclass
class LabelledPairs:
    """Keypoint index pairs of one frame pair with labels (1 = same 3-D point, 0 = different)."""

    idx_a: np.ndarray
    idx_b: np.ndarray
    label: np.ndarray
    kind: np.ndarray  # POSITIVE, HARD_NEGATIVE or RANDOM_NEGATIVE
    anchors: dict[str, int]  # visible / occluded anchors used, moved ones left out


def label_pairs(frame_a: CachedFrame, frame_b: CachedFrame, geometry: PairGeometry, conf: LabelConfig,
                rng: np.random.Generator) -> LabelledPairs:
    """Positive and negative keypoint pairs between two frames.

    Anchors are A's keypoints with depth whose projection lands in B, by ``geometry.visibility_a``:

    * VISIBLE anchors (B's depth confirms the projection) give positives and negatives;
    * OCCLUDED anchors (something nearer hides the point in B) have no true match in B, so every
      candidate is a negative: exactly the wrong matches nearest-neighbour search makes around people;
    * MOVED anchors (B sees something farther there: the point moved, e.g. a walking person) are left
      out: the static-world ground truth cannot say where they went, so any label would be a guess.

    For each anchor, the positive is the keypoint of B nearest the projection, when within
    ``positive_px``, its own depth agrees with the projected depth and its back-projection lands within
    ``positive_px`` of the anchor. Hard negatives are the anchor's ``hard_negatives`` descriptor nearest
    neighbours in B farther than ``negative_px`` from the projection (occluded anchors: all of them);
    random negatives are random such keypoints. Keypoints between ``positive_px`` and ``negative_px``
    from the projection are ambiguous and never used.
    """
    if geometry.visibility_a is None:
        raise ValueError("label_pairs needs PairGeometry computed with B's depth map")
    kp_a, kp_b = frame_a.keypoints, frame_b.keypoints
    visibility = geometry.visibility_a
    counts = {"visible": int((visibility == VISIBLE).sum()), "occluded": int((visibility == OCCLUDED).sum()),
              "moved_left_out": int((visibility == MOVED).sum())}
    usable = (visibility == VISIBLE) | ((visibility == OCCLUDED) & conf.occluded_anchors)
    anchors = np.flatnonzero(usable)
    empty = np.zeros(0, np.int64)
    if len(anchors) == 0 or len(kp_b) == 0:
        return LabelledPairs(empty, empty, empty.astype(np.float32), empty.astype(np.int8), counts)
    if len(anchors) > conf.max_anchors:
        anchors = np.sort(rng.choice(anchors, conf.max_anchors, replace=False))
    visible = visibility[anchors] == VISIBLE
    counts["sampled"] = len(anchors)

    pixel_dist = np.linalg.norm(geometry.xy_ab[anchors, None, :] - kp_b.xy[None, :, :], axis=2)  # (A, Nb)
    nearest = pixel_dist.argmin(1)
    nearest_dist = pixel_dist[np.arange(len(anchors)), nearest]
    with np.errstate(invalid="ignore"):
        back_err = np.linalg.norm(geometry.xy_ba[nearest] - kp_a.xy[anchors], axis=1)
        positive = visible & (nearest_dist <= conf.positive_px) & (back_err <= conf.positive_px) & \
            depth_agrees(geometry.z_ab[anchors], frame_b.depth_at_keypoints[nearest], conf.depth_tolerance)
    # an occluded anchor has no match in B: nothing near its projection is the same point
    far = (pixel_dist > conf.negative_px) | ~visible[:, None]

    rows_a, rows_b, labels, kinds = [anchors[positive]], [nearest[positive]], [np.ones(positive.sum())], \
        [np.full(positive.sum(), POSITIVE)]
    if conf.hard_negatives > 0:
        k = min(conf.hard_negatives, len(kp_b))
        dist = descriptor_distances(kp_a.descriptors[anchors], kp_b.descriptors, squared=True)
        knn = np.argpartition(dist, k - 1, axis=1)[:, :k]
        r, c = np.nonzero(np.take_along_axis(far, knn, 1))
        rows_a.append(anchors[r])
        rows_b.append(knn[r, c])
        labels.append(np.zeros(len(r)))
        kinds.append(np.full(len(r), HARD_NEGATIVE))
    if conf.random_negatives > 0:
        picks = rng.integers(0, len(kp_b), size=(len(anchors), conf.random_negatives))
        r, c = np.nonzero(np.take_along_axis(far, picks, 1))
        rows_a.append(anchors[r])
        rows_b.append(picks[r, c])
        labels.append(np.zeros(len(r)))
        kinds.append(np.full(len(r), RANDOM_NEGATIVE))
    return LabelledPairs(np.concatenate(rows_a).astype(np.int64), np.concatenate(rows_b).astype(np.int64),
                         np.concatenate(labels).astype(np.float32), np.concatenate(kinds).astype(np.int8), counts)


# ----------------------------------------------------------------------------- splits and pair sets


class SplitConfig(BaseModel):
    """Split of a sequence by time (paper: 80/20). The first 80 % is train + validation, the rest is held out."""

    val_start: float = Field(0.7, gt=0, lt=1, description="validation starts at this fraction of the frames")
    test_start: float = Field(0.8, gt=0, lt=1, description="held-out test starts at this fraction of the frames")
    step: int = Field(2, ge=1, description="use every step-th frame")
    deltas: list[int] = Field(default_factory=lambda: [2, 4, 6, 10], description="frame gaps of the pairs")


def split_frames(num_frames: int, conf: SplitConfig) -> dict[str, list[int]]:
    """Frame indices (every ``step``-th) of the train, val and test parts, contiguous in time."""
    if not conf.val_start < conf.test_start:
        raise ValueError("val_start must come before test_start")
    val0, test0 = int(round(conf.val_start * num_frames)), int(round(conf.test_start * num_frames))
    frames = range(0, num_frames, conf.step)
    return {"train": [i for i in frames if i < val0], "val": [i for i in frames if val0 <= i < test0],
            "test": [i for i in frames if i >= test0]}


def frame_pairs(frames: list[int], deltas: list[int]) -> list[tuple[int, int]]:
    """All pairs (i, i + delta) with both frames in ``frames``, so no pair straddles a split."""
    available = set(frames)
    return [(i, i + d) for d in sorted(set(deltas)) for i in frames if i + d in available]


@dataclass
class PairSet:
    """Labelled descriptor pairs of many frame pairs, stored as indices into one descriptor bank."""

    bank: np.ndarray  # (K, D) float16 descriptors of all frames used
    idx_a: np.ndarray  # (P,) rows of bank
    idx_b: np.ndarray
    label: np.ndarray  # (P,) float32
    kind: np.ndarray  # (P,) int8: 0 positive, 1 hard negative, 2 random negative
    delta: np.ndarray  # (P,) frame gap
    anchors: dict[str, int]  # totals of LabelledPairs.anchors
    frame_pairs: int
    frame_pairs_failing_gt_check: int = 0

    def __len__(self) -> int:
        return len(self.label)

    def counts(self) -> dict[str, int]:
        return {"frame_pairs": self.frame_pairs, "frame_pairs_failing_gt_check": self.frame_pairs_failing_gt_check,
                "pairs": len(self),
                "positives": int((self.kind == POSITIVE).sum()),
                "hard_negatives": int((self.kind == HARD_NEGATIVE).sum()),
                "random_negatives": int((self.kind == RANDOM_NEGATIVE).sum()),
                **{f"anchors_{k}": v for k, v in self.anchors.items()}}


def build_pair_set(cache: KeypointCache, pairs: list[tuple[int, int]], conf: LabelConfig, seed: int = 0,
                   progress: bool = True) -> PairSet:
    """Label every frame pair of ``pairs`` (keypoints must be cached) into one :class:`PairSet`."""
    from tqdm import tqdm

    rng = np.random.default_rng(seed)
    camera = cache.sequence.camera
    k = camera.matrix
    offsets: dict[int, int] = {}
    bank: list[np.ndarray] = []
    size = 0
    frames: dict[int, CachedFrame] = {}
    depth_maps: dict[int, np.ndarray] = {}
    out_a, out_b, labels, kinds, deltas = [], [], [], [], []
    anchors: dict[str, int] = {}
    used = skipped = 0
    for a, b in tqdm(pairs, desc="labelling", unit="pair", disable=not progress):
        for i in (a, b):
            if i not in frames:
                frames[i] = cache.load(i)
                offsets[i] = size
                bank.append(frames[i].keypoints.descriptors.astype(np.float16))
                size += len(frames[i].keypoints)
        if frames[a].pose is None or frames[b].pose is None:
            continue
        if b not in depth_maps:
            depth_maps[b] = cache.sequence.read(b).depth
        geometry = pair_geometry(frames[a], frames[b], k, camera.width, camera.height, depth_maps[b],
                                 conf.depth_tolerance)
        if keypoint_repeatability(geometry, frames[b].keypoints.xy, conf.positive_px) < conf.min_pair_repeatability:
            skipped += 1
            continue
        labelled = label_pairs(frames[a], frames[b], geometry, conf, rng)
        used += 1
        out_a.append(labelled.idx_a + offsets[a])
        out_b.append(labelled.idx_b + offsets[b])
        labels.append(labelled.label)
        kinds.append(labelled.kind)
        deltas.append(np.full(len(labelled.label), b - a, np.int16))
        for key, value in labelled.anchors.items():
            anchors[key] = anchors.get(key, 0) + value

    def cat(parts: list[np.ndarray], dtype) -> np.ndarray:
        return np.concatenate(parts).astype(dtype) if parts else np.zeros(0, dtype)

    dim = bank[0].shape[1] if bank else 128
    return PairSet(np.concatenate(bank) if bank else np.zeros((0, dim), np.float16), cat(out_a, np.int64),
                   cat(out_b, np.int64), cat(labels, np.float32), cat(kinds, np.int8), cat(deltas, np.int16),
                   anchors, used, skipped)
