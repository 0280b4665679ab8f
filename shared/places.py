"""Place recognition on our own features: a visual vocabulary over 2HR descriptors, a bag-of-words vector per
keyframe, and an index of keyframes searched by that vector.

A :class:`Vocabulary` is trained once (``twohr vocab train``: k-means over the 2HR descriptors of a sequence's
frames) and kept as one ``.npz`` file with its model card beside it. A keyframe's vector is the tf-idf weighted
histogram of the words of its described landmarks, L2-normalised, so that the dot product of two vectors (their
cosine) says how alike two places look. :class:`PlaceIndex` holds the vectors of a map's keyframes; faiss is not
needed at the size of a room's map (hundreds of keyframes: one matrix product).

:func:`verify` checks a candidate place geometrically: descriptor matches, RANSAC PnP, the pose refined with depth,
and a view-change gate. The tracker's loop closer and the map server's search across robots share it.
"""

from __future__ import annotations

import json
import os
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from twohr.config import LoopClosingConfig, TrackerConfig
from twohr.errors import TwohrError
from twohr.features import Matches
from twohr.files import AS_OPEN, replacing
from twohr.geometry import invert_pose
from twohr.models import cache_dir
from twohr.pose import matched_pnp, pose_difference, refine_pose

MatchFn = Callable[[np.ndarray, np.ndarray], Matches]

VOCABULARY_FORMAT = 1
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


class VocabularyError(TwohrError):
    """A vocabulary file that is missing, unreadable or not one of ours."""


def vocabulary_dir() -> Path:
    """Where installed vocabularies live: ``$TWOHR_VOCABULARIES``, else ``$TWOHR_CACHE/vocabularies`` (beside the
    model cache)."""
    return Path(os.environ.get("TWOHR_VOCABULARIES") or cache_dir().parent / "vocabularies")


def vocabulary_path(name: str) -> Path:
    """The installed vocabulary ``name`` (a plain name, never a path: sessions over HTTP may name one)."""
    if not _NAME.match(name):
        raise VocabularyError(f"vocabulary name {name!r}: letters, digits, '.', '_' and '-' only")
    return vocabulary_dir() / f"{name}.npz"


@dataclass
class Vocabulary:
    """``words`` (W, D) unit vectors, the k-means centres of descriptors; ``idf`` (W,) the inverse document
    frequency of each word over the training frames; ``card`` what it was trained on, and how."""

    words: np.ndarray
    idf: np.ndarray
    card: dict

    @classmethod
    def train(cls, descriptor_sets: list[np.ndarray], num_words: int, iterations: int = 20, seed: int = 0,
              card: dict | None = None) -> Vocabulary:
        """k-means (k-means++ seeding) of all descriptors of ``descriptor_sets`` (one (N_i, D) array per frame)
        into ``num_words`` words; each frame is one document for the idf."""
        sets = [np.asarray(d, np.float32) for d in descriptor_sets if len(d)]
        everything = np.concatenate(sets) if sets else np.zeros((0, 0), np.float32)
        if len(everything) < num_words:
            raise VocabularyError(f"{len(everything)} descriptors cannot make {num_words} words")
        cv2.setRNGSeed(seed)
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, iterations, 1e-4)
        _, _, centres = cv2.kmeans(everything, num_words, None, criteria, 1, cv2.KMEANS_PP_CENTERS)
        words = _unit(centres)
        vocabulary = cls(words, np.ones(num_words, np.float32), dict(card or {}))
        documents = np.zeros(num_words)
        for descriptors in sets:
            documents[np.unique(vocabulary.assign(descriptors))] += 1
        vocabulary.idf = np.log(len(sets) / (1.0 + documents)).clip(0).astype(np.float32)
        vocabulary.card.update(words=num_words, descriptors=len(everything), documents=len(sets),
                               dimension=int(words.shape[1]))
        return vocabulary

    @property
    def size(self) -> int:
        return len(self.words)

    def assign(self, descriptors: np.ndarray) -> np.ndarray:
        """(N,) the word of each descriptor: the nearest centre (greatest cosine)."""
        return np.argmax(np.asarray(descriptors, np.float32) @ self.words.T, axis=1)

    def vector(self, descriptors: np.ndarray) -> np.ndarray:
        """(W,) the place's bag of words: tf-idf weighted word counts, L2-normalised (zero for no descriptors)."""
        counts = np.bincount(self.assign(descriptors), minlength=self.size).astype(np.float32) if len(
            descriptors) else np.zeros(self.size, np.float32)
        weighted = counts * self.idf
        norm = np.linalg.norm(weighted)
        return weighted / norm if norm > 0 else weighted

    def save(self, path: Path) -> None:
        """Write the ``.npz`` atomically; the card goes inside, as JSON."""
        with replacing(path, AS_OPEN) as fh:
            np.savez(fh, words=self.words, idf=self.idf, format=np.int64(VOCABULARY_FORMAT),
                     card=np.frombuffer(json.dumps(self.card).encode(), np.uint8))

    @classmethod
    def load(cls, path: Path) -> Vocabulary:
        try:
            with np.load(path, allow_pickle=False) as data:
                if int(data["format"]) != VOCABULARY_FORMAT:
                    raise VocabularyError(f"{path}: vocabulary format {int(data['format'])}, this build reads "
                                          f"{VOCABULARY_FORMAT}")
                words, idf = data["words"].astype(np.float32), data["idf"].astype(np.float32)
                card = json.loads(data["card"].tobytes().decode())
        except FileNotFoundError:
            raise VocabularyError(f"no vocabulary at {path}: train one with `twohr vocab train`") from None
        except (OSError, KeyError, ValueError) as exc:
            raise VocabularyError(f"{path} is not a twohr vocabulary: {exc}") from None
        if words.ndim != 2 or idf.shape != (len(words),):
            raise VocabularyError(f"{path}: words {words.shape} and idf {idf.shape} do not fit")
        return cls(_unit(words), idf, card)


class PlaceIndex:
    """The bag-of-words vectors of a map's keyframes, searched by cosine similarity."""

    def __init__(self, size: int) -> None:
        self.ids = np.zeros(0, np.int64)
        self.vectors = np.zeros((0, size), np.float32)

    def __len__(self) -> int:
        return len(self.ids)

    def add(self, keyframe_id: int, vector: np.ndarray) -> None:
        self.ids = np.append(self.ids, keyframe_id)
        self.vectors = np.vstack([self.vectors, vector[None].astype(np.float32)])

    def scores(self, vector: np.ndarray) -> dict[int, float]:
        """Every indexed keyframe's similarity to ``vector``."""
        return dict(zip(self.ids.tolist(), (self.vectors @ vector).tolist(), strict=True))

    def search(self, vector: np.ndarray, count: int, allowed=None) -> list[tuple[int, float]]:
        """The ``count`` most similar keyframes as (id, score), best first; ``allowed(id)`` filters."""
        if not len(self.ids):
            return []
        scores = self.vectors @ vector
        order = np.argsort(-scores, kind="stable")
        found = [(int(self.ids[i]), float(scores[i])) for i in order if allowed is None or allowed(int(self.ids[i]))]
        return found[:count]


def _unit(vectors: np.ndarray) -> np.ndarray:
    vectors = np.asarray(vectors, np.float32)
    return vectors / np.maximum(np.linalg.norm(vectors, axis=1, keepdims=True), 1e-12)


@dataclass
class PlaceCandidate:
    """An older keyframe that looks like the query, with the landmarks it and its neighbours observe."""

    keyframe_id: int
    score: float
    landmark_ids: np.ndarray
    positions: np.ndarray
    descriptors: np.ndarray
    pose: np.ndarray
    """the candidate keyframe's camera-to-world pose"""


@dataclass
class PlaceQuery:
    """What verification needs of a keyframe and its candidates: copies, so that the map may change meanwhile."""

    keyframe_id: int
    stamp: float
    xy: np.ndarray
    depth: np.ndarray
    landmark_ids: np.ndarray
    descriptors: np.ndarray
    candidates: list[PlaceCandidate]


@dataclass
class PlaceMatch:
    """A verified place (a loop to the loop closer, a match across robots to the map server): keyframe
    ``keyframe_id`` seen again from candidate ``candidate_id``'s part of the map, at camera-to-world pose
    ``relative`` in the candidate keyframe's frame (relative, so that bundle adjustment moving both meanwhile does not
    matter); ``pairs`` (M, 2) the inlier (keyframe's landmark, candidate's landmark) pairs."""

    keyframe_id: int
    candidate_id: int
    score: float
    relative: np.ndarray
    pairs: np.ndarray
    stamp: float = 0.0
    candidate_stamp: float = 0.0


@dataclass
class PlaceVerdict:
    """The outcome of verifying one query: a :class:`PlaceMatch`, or None and why not."""

    match: PlaceMatch | None
    reason: str
    ms: float = 0.0


def verify(query: PlaceQuery, K: np.ndarray, conf: LoopClosingConfig, tracking: TrackerConfig,
           match: MatchFn) -> PlaceVerdict:
    """Geometric verification of a query's candidates (best first): descriptor matches, RANSAC PnP of the
    keyframe's keypoints against the candidates' landmarks, then the pose refined on the inliers with their depth
    (as tracking refines a frame's pose). Pure: reads only the query."""
    t0 = time.perf_counter()
    best_inliers, best_reason = 0, ""
    for candidate in query.candidates:
        matched = matched_pnp(K, match, query.descriptors, query.xy, candidate.descriptors, candidate.positions,
                              conf.min_inliers, tracking.ransac_reprojection_px, tracking.ransac_iterations)
        if matched is None:
            continue
        T_cw, a, b, inliers = matched
        found = int(inliers.sum())
        best_inliers = max(best_inliers, found)
        if T_cw is not None and found >= conf.min_inliers:
            a, b = a[inliers], b[inliers]
            T_cw = refine_pose(K, T_cw, candidate.positions[b], query.xy[a], query.depth[a], tracking.depth_noise,
                               tracking.huber_px)
            metres, degrees = pose_difference(candidate.pose, invert_pose(T_cw))
            if metres > conf.max_view_change_m or degrees > conf.max_view_change_deg:
                # the same landmarks, seen from far apart: a wide-baseline match is the likelier mistake
                best_reason = f"keyframe {candidate.keyframe_id} seen from {metres:.2f} m, {degrees:.0f} deg away"
                continue
            pairs = np.stack([query.landmark_ids[a], candidate.landmark_ids[b]], axis=1)
            relative = invert_pose(candidate.pose) @ invert_pose(T_cw)
            verified = PlaceMatch(query.keyframe_id, candidate.keyframe_id, candidate.score, relative, pairs,
                                  query.stamp)
            return PlaceVerdict(verified, f"{found} inliers against keyframe {candidate.keyframe_id}",
                               (time.perf_counter() - t0) * 1000)
    reason = best_reason or f"best {best_inliers} inliers < {conf.min_inliers}"
    return PlaceVerdict(None, reason, (time.perf_counter() - t0) * 1000)
