"""The matcher core: descriptor correspondences between two keypoint sets. Arrays in, matches out.

Baselines: mutual nearest neighbour and Lowe's ratio test, for float (L2-normalised) and packed
binary (Hamming) descriptors. The paper's matcher: :class:`SiameseMatcher`, a learned similarity
(the lab's matching model, ``lab/matching/model.py``, exported to ONNX) that scores the k nearest candidates;
it runs on onnxruntime alone.
:func:`build_matcher` returns the method a :class:`~twohr.config.MatcherConfig` names.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from functools import cache
from pathlib import Path

import numpy as np
import onnxruntime as ort

from twohr.config import MatcherConfig
from twohr.errors import ModelError
from twohr.features import Matches, descriptor_distances, mutual_nn
from twohr.models import cpu_session, model_path

log = logging.getLogger(__name__)

__all__ = ["SiameseMatcher", "build_matcher", "descriptor_distances", "knn_candidates", "mutual_best", "mutual_nn",
           "ratio_test"]


def ratio_test(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float = 0.8, mutual: bool = True) -> Matches:
    """Lowe's ratio test (nearest / second nearest < ratio), optionally also mutual; score = -distance."""
    if len(desc_a) == 0 or len(desc_b) < 2:
        return Matches.empty()
    dist = descriptor_distances(desc_a, desc_b)
    two = np.argpartition(dist, 1, axis=1)[:, :2]
    d2 = np.take_along_axis(dist, two, 1)
    order = np.argsort(d2, axis=1)
    best = np.take_along_axis(two, order, 1)[:, 0]
    d_sorted = np.take_along_axis(d2, order, 1)
    keep = d_sorted[:, 0] < ratio * d_sorted[:, 1]
    if mutual:
        keep &= dist.argmin(0)[best] == np.arange(len(desc_a))
    idx_a = np.flatnonzero(keep)
    return Matches(idx_a, best[idx_a], (-d_sorted[idx_a, 0]).astype(np.float32))


# ----------------------------------------------------------------------------- the Siamese matcher


def _check_descriptors(desc_a: np.ndarray, desc_b: np.ndarray) -> None:
    for name, desc in (("desc_a", desc_a), ("desc_b", desc_b)):
        if not isinstance(desc, np.ndarray) or desc.ndim != 2:
            raise ValueError(f"{name} must be a 2-D array (N, D), got {getattr(desc, 'shape', type(desc).__name__)}")
    if desc_a.shape[1] != desc_b.shape[1] or (desc_a.dtype == np.uint8) != (desc_b.dtype == np.uint8):
        raise ValueError(f"descriptors differ: {desc_a.shape} {desc_a.dtype} vs {desc_b.shape} {desc_b.dtype}")


#: score-matrix entries (float32) that :func:`knn_candidates` holds at once: 16 MB
KNN_BLOCK = 1 << 22


@cache
def _session(path: str, threads: int) -> ort.InferenceSession:
    return cpu_session(path, threads, varying_shapes=True)  # candidate lists differ in length on every call


def knn_candidates(desc_a: np.ndarray, desc_b: np.ndarray, k: int,
                   block: int = KNN_BLOCK) -> tuple[np.ndarray, np.ndarray]:
    """Candidate pairs (idx_a, idx_b), each of A's descriptors with its ``k`` nearest in B (Euclidean).

    The (Na, Nb) score matrix is built ``block`` entries at a time (whole rows of A), so a whole-map query
    needs no more memory than a small one."""
    k = min(k, len(desc_b))
    a = desc_a.astype(np.float32, copy=False)
    b = desc_b.astype(np.float32, copy=False)
    half_norm = 0.5 * (b * b).sum(1)
    nearest = np.empty((len(a), k), np.int64)
    step = max(1, block // max(len(b), 1))
    for start in range(0, len(a), step):
        # nearest = largest a.b - |b|^2 / 2 (|a - b|^2 without the row constant |a|^2). k rounds of argmax and
        # masking beat a full argpartition of the (Na, Nb) matrix for small k (3 ms vs 8 ms at 1000 x 1000)
        score = a[start:start + step] @ b.T
        score -= half_norm[None, :]
        rows = np.arange(len(score))
        for j in range(k):
            best = score.argmax(1)
            nearest[start:start + step, j] = best
            score[rows, best] = -np.inf
    return np.repeat(np.arange(len(a)), k), nearest.reshape(-1)


def mutual_best(idx_a: np.ndarray, idx_b: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """Indices of the candidate pairs whose score is the best both for their ``a`` and for their ``b``."""
    if len(scores) == 0:
        return np.zeros(0, np.int64)

    def best_per(group: np.ndarray) -> np.ndarray:
        order = np.lexsort((-scores, group))  # by group, best score first
        first = np.ones(len(order), bool)
        first[1:] = group[order][1:] != group[order][:-1]
        is_best = np.zeros(len(scores), bool)
        is_best[order[first]] = True
        return is_best

    return np.flatnonzero(best_per(idx_a) & best_per(idx_b))


class SiameseMatcher:
    """The paper's Siamese matcher: k-NN candidates scored by the learned head, mutual best and score >= tau.

    1. candidates: each descriptor of A with its ``conf.candidates`` nearest descriptors of B;
    2. the Siamese network scores the candidates, at most ``conf.max_pairs_per_call`` of them per onnxruntime
       call;
    3. a pair is kept when it is the best-scoring candidate of its ``a`` *and* of its ``b`` and its
       score is at least ``conf.threshold``.

    Packed binary descriptors (ORB) have no learned head: they fall back to Hamming mutual nearest
    neighbours, with a warning.
    """

    default_conf = MatcherConfig()

    def __init__(self, conf: MatcherConfig | None = None, model_file: str | Path | None = None) -> None:
        self.conf = conf or self.default_conf
        path = Path(model_file) if model_file is not None else model_path(self.conf.model, kind="siamese")
        if not path.is_file():
            raise ModelError(f"Siamese matcher model not found: {path}")
        try:
            self.session = _session(str(path), self.conf.threads)
        except Exception as exc:  # onnxruntime raises its own exception types for unreadable files
            raise ModelError(f"cannot load the Siamese matcher model {path}: {exc}") from None
        self.descriptor_dim = self.session.get_inputs()[0].shape[1]
        self._warned_binary = False

    def score(self, desc_a: np.ndarray, desc_b: np.ndarray, idx_a: np.ndarray, idx_b: np.ndarray) -> np.ndarray:
        """Siamese similarity in [0, 1] of the pairs ``(desc_a[idx_a], desc_b[idx_b])``.

        One onnxruntime call takes at most ``conf.max_pairs_per_call`` pairs and as many descriptors of each side.
        A larger query (a whole-map relocalisation) runs in chunks of pairs, each with only the descriptors it
        uses: the same scores, and the session's memory stays bounded whatever the query's size."""
        if len(idx_a) == 0:
            return np.zeros(0, np.float32)
        cap = self.conf.max_pairs_per_call
        if len(idx_a) <= cap and len(desc_a) <= cap and len(desc_b) <= cap:
            return self._run(desc_a, desc_b, idx_a, idx_b)
        idx_a, idx_b = np.asarray(idx_a), np.asarray(idx_b)
        scores = np.empty(len(idx_a), np.float32)
        for start in range(0, len(idx_a), cap):
            chunk = slice(start, start + cap)
            used_a, local_a = np.unique(idx_a[chunk], return_inverse=True)
            used_b, local_b = np.unique(idx_b[chunk], return_inverse=True)
            scores[chunk] = self._run(desc_a[used_a], desc_b[used_b], local_a, local_b)
        return scores

    def _run(self, desc_a: np.ndarray, desc_b: np.ndarray, idx_a: np.ndarray, idx_b: np.ndarray) -> np.ndarray:
        return self.session.run(["scores"], {
            "desc_a": np.ascontiguousarray(desc_a, np.float32), "desc_b": np.ascontiguousarray(desc_b, np.float32),
            "idx_a": np.ascontiguousarray(idx_a, np.int64), "idx_b": np.ascontiguousarray(idx_b, np.int64),
        })[0]

    def match(self, desc_a: np.ndarray, desc_b: np.ndarray) -> Matches:
        """Matches between descriptor sets (Na, D) and (Nb, D); ``scores`` are the Siamese similarities."""
        _check_descriptors(desc_a, desc_b)
        if desc_a.dtype == np.uint8:
            if not self._warned_binary:
                log.warning("binary descriptors have no Siamese head: falling back to Hamming mutual nearest "
                            "neighbours")
                self._warned_binary = True
            return mutual_nn(desc_a, desc_b)
        if desc_a.shape[1] != self.descriptor_dim:
            raise ValueError(f"the Siamese model expects {self.descriptor_dim}-D descriptors, got {desc_a.shape[1]}")
        if len(desc_a) == 0 or len(desc_b) == 0:
            return Matches.empty()
        idx_a, idx_b = knn_candidates(desc_a, desc_b, self.conf.candidates)
        scores = self.score(desc_a, desc_b, idx_a, idx_b)
        keep = mutual_best(idx_a, idx_b, scores)
        keep = keep[scores[keep] >= self.conf.threshold]
        return Matches(idx_a[keep], idx_b[keep], scores[keep].astype(np.float32))

    __call__ = match


def build_matcher(conf: MatcherConfig | None = None) -> Callable[[np.ndarray, np.ndarray], Matches]:
    """A ``(desc_a, desc_b) -> Matches`` function for ``conf.method``: siamese, mutual_nn or ratio."""
    conf = conf or MatcherConfig()
    if conf.method == "siamese":
        return SiameseMatcher(conf).match
    if conf.method == "mutual_nn":
        return lambda desc_a, desc_b: mutual_nn(desc_a, desc_b)
    return lambda desc_a, desc_b: ratio_test(desc_a, desc_b, conf.ratio)
