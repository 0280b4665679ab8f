"""Loop closing: a keyframe that sees a place the map already holds, far back along the path, pulls the drift out.

Three steps, split by the thread they may run on:

1. :meth:`LoopClosing.query` (mapping worker, after a keyframe joins the map): the keyframe's bag of words
   (:mod:`twohr.places`) is searched among keyframes at least ``min_separation`` keyframes older that share no more
   than a few landmarks with it; the best candidates come back as a :class:`PlaceQuery`, a copy of what
   verification needs, and the keyframe joins the index.
2. :func:`twohr.places.verify` (its own worker, reads no map): the keyframe's landmark descriptors are matched
   to the landmarks of each candidate and its neighbours, and RANSAC PnP must find ``min_inliers`` inliers: that
   gives the keyframe's pose in the candidate's frame (:class:`~twohr.places.PlaceMatch`), or a reason for rejecting it.
3. :meth:`LoopClosing.close` (mapping worker): a pose graph (gtsam) over the keyframe chain plus the loop edge
   spreads the correction along the path; every landmark moves with the keyframe that first observed it; the
   loop's matched landmarks are fused (the keyframe's duplicates retired); bundle adjustment over the whole map
   follows.
"""

from __future__ import annotations

import importlib.util
import logging
from dataclasses import dataclass, field

import numpy as np

from twohr.config import LoopClosingConfig
from twohr.errors import TwohrError
from twohr.geometry import invert_pose
from twohr.places import PlaceCandidate, PlaceIndex, PlaceMatch, PlaceQuery, Vocabulary
from twohr.pose import pose_difference

from .map import Map

log = logging.getLogger("twohr.loops")


@dataclass
class LoopLog:
    """The loops of a session: counts for ``summary.json`` and the status, and every accepted loop."""

    detected: int = 0
    accepted: int = 0
    rejected: int = 0
    closed: int = 0
    loops: list[dict] = field(default_factory=list)

    def as_dict(self) -> dict:
        return {"detected": self.detected, "accepted": self.accepted, "rejected": self.rejected,
                "closed": self.closed, "loops": self.loops}


class LoopClosing:
    """Place recognition over one :class:`~.map.Map` and the correction of verified loops (see the module
    docstring). ``query`` and ``close`` run where the map is written (the mapping worker)."""

    def __init__(self, world: Map, vocabulary: Vocabulary, conf: LoopClosingConfig) -> None:
        if importlib.util.find_spec("gtsam") is None:
            raise TwohrError("loop closing needs gtsam for its pose graph: pip install gtsam")
        self.map = world
        self.vocabulary = vocabulary
        self.conf = conf
        self.index = PlaceIndex(vocabulary.size)
        self.off = ""  # why loop closing stopped (a vocabulary for other descriptors)
        self._indexed: set[int] = set()
        if self._fits():
            for keyframe in world.keyframes:  # a map loaded from a file: its keyframes are places already
                self._index(keyframe.id)

    def _fits(self) -> bool:
        """Whether the vocabulary's words fit the map's descriptors; when they do not (a vocabulary trained for
        another detector), loop closing turns itself off, said once, and the keyframe jobs go on."""
        descriptors = self.map.landmarks.descriptors
        if not self.off and descriptors is not None and descriptors.shape[1] != self.vocabulary.words.shape[1]:
            self.off = (f"loop closing off: vocabulary {self.vocabulary.card.get('name', '?')} has "
                        f"{self.vocabulary.words.shape[1]}-D words, the map's descriptors are {descriptors.shape[1]}-D")
            log.warning(self.off)
        return not self.off

    def _observed(self, keyframe_id: int) -> np.ndarray:
        """Keypoint indices of a keyframe that observe a described, usable landmark."""
        landmarks = self.map.landmarks
        ids = self.map.keyframes[keyframe_id].landmark_ids
        usable = ids >= 0
        usable[usable] = ~landmarks.bad[ids[usable]] & landmarks.described[ids[usable]]
        return np.flatnonzero(usable)

    def _vector(self, keyframe_id: int) -> np.ndarray:
        ids = self.map.keyframes[keyframe_id].landmark_ids[self._observed(keyframe_id)]
        return self.vocabulary.vector(self.map.landmarks.descriptors[ids])

    def _index(self, keyframe_id: int) -> None:
        if keyframe_id not in self._indexed and not self.map.keyframes[keyframe_id].culled:
            self.index.add(keyframe_id, self._vector(keyframe_id))
            self._indexed.add(keyframe_id)

    def query(self, keyframe_id: int) -> PlaceQuery | None:
        """Candidates for a loop at keyframe ``keyframe_id`` (None: none worth verifying); the keyframe then joins
        the index. A candidate must be ``min_separation`` keyframes older, score at least ``min_score_ratio`` of
        the keyframe's best score against its 3 predecessors (how alike views of one place are here), and share at most
        ``max_shared_landmarks`` of the keyframe's landmarks (more: the map already joins them)."""
        conf, world = self.conf, self.map
        if not self._fits():
            return None
        keyframe = world.keyframes[keyframe_id]
        observed = self._observed(keyframe_id)
        query = None
        if len(observed) >= self.conf.min_inliers and keyframe_id >= conf.min_separation:
            vector = self._vector(keyframe_id)
            scores = self.index.scores(vector)
            reference = max((scores.get(k, 0.0) for k in range(keyframe_id - 3, keyframe_id)), default=0.0)
            own = set(keyframe.landmark_ids[observed].tolist())
            candidates = []
            for candidate_id, score in self.index.search(
                    vector, 4 * conf.candidates, lambda k: k <= keyframe_id - conf.min_separation):
                if score < max(conf.min_score, conf.min_score_ratio * reference) or len(candidates) >= conf.candidates:
                    break
                neighbours = self._neighbours(candidate_id)
                ids = world.usable_landmarks(neighbours, described=True) if len(neighbours) else np.zeros(0, int)
                if len(ids) < conf.min_inliers or \
                        len(own.intersection(ids.tolist())) > conf.max_shared_landmarks * len(observed):
                    continue
                candidates.append(PlaceCandidate(candidate_id, score, ids, world.landmarks.positions[ids].copy(),
                                                world.landmarks.descriptors[ids].copy(),
                                                world.keyframe_poses[candidate_id].copy()))
            if candidates:
                ids = keyframe.landmark_ids[observed]
                query = PlaceQuery(keyframe_id, keyframe.stamp, keyframe.xy[observed].copy(),
                                  keyframe.depth[observed].copy(), ids.copy(),
                                  world.landmarks.descriptors[ids].copy(), candidates)
        self._index(keyframe_id)
        return query

    def _neighbours(self, keyframe_id: int) -> np.ndarray:
        """The candidate and the keyframes next to it on the path (not culled): its part of the map."""
        reach = self.conf.candidate_neighbours
        span = range(max(0, keyframe_id - reach), min(len(self.map.keyframes), keyframe_id + reach + 1))
        return np.array([k for k in span if not self.map.keyframes[k].culled], np.int64)

    def close(self, loop: PlaceMatch, ba_iterations: int) -> dict:
        """Correct the map for a verified loop; returns what it moved (the keyframe's correction, in m and deg)."""
        world = self.map
        before = world.keyframe_poses.copy()
        corrected = before[loop.candidate_id] @ loop.relative
        metres, degrees = pose_difference(before[loop.keyframe_id], corrected)
        poses = optimise_pose_graph(before, loop.candidate_id, loop.keyframe_id, corrected, self.conf, self._joined())
        self._move_landmarks(before, poses)
        world.keyframe_poses = poses
        world.corrections += 1
        self._fuse(loop.pairs)
        if ba_iterations > 0:
            first = max(0, len(world.keyframes) - world.conf.final_ba_max_keyframes)
            world.bundle_adjust(np.arange(first, len(world.keyframes)), ba_iterations)
        return {"keyframe": loop.keyframe_id, "candidate": loop.candidate_id, "stamp": loop.stamp,
                "candidate_stamp": float(world.keyframes[loop.candidate_id].stamp), "score": round(loop.score, 4),
                "inliers": len(loop.pairs), "correction_m": round(metres, 4), "correction_deg": round(degrees, 3)}

    def _joined(self) -> np.ndarray:
        """(K,) whether each keyframe shares landmarks with the keyframe before it (culled ones are skipped over):
        after a loss the map starts again at a coasted guess, and that step of the path is no measurement."""
        joined = np.ones(len(self.map.keyframes), bool)
        previous = None
        for keyframe in self.map.keyframes:
            if keyframe.culled:
                continue
            observed = keyframe.landmark_ids[keyframe.landmark_ids >= 0]
            if previous is not None:
                joined[keyframe.id] = len(np.intersect1d(previous, observed)) > 0
            previous = observed
        return joined

    def _move_landmarks(self, before: np.ndarray, after: np.ndarray) -> None:
        """Every landmark moves rigidly with the first keyframe that observes it; one that no keyframe observes any
        more (its observations cut as outliers, or only culled keyframes saw it) cannot be moved and is retired."""
        landmarks = self.map.landmarks
        reference = np.full(len(landmarks), -1, np.int64)
        for keyframe in self.map.keyframes:
            ids = keyframe.landmark_ids[keyframe.landmark_ids >= 0]
            fresh = ids[reference[ids] < 0]
            reference[fresh] = keyframe.id
        landmarks.bad[reference < 0] = True
        for k in np.unique(reference[reference >= 0]):
            ids = np.flatnonzero(reference == k)
            motion = after[k] @ invert_pose(before[k])
            landmarks.positions[ids] = landmarks.positions[ids] @ motion[:3, :3].T + motion[:3, 3]

    def _fuse(self, pairs: np.ndarray) -> None:
        """The keyframe's landmarks of the loop's inlier pairs are the candidate's: observations move over and the
        duplicates retire."""
        landmarks = self.map.landmarks
        duplicate, original = pairs[:, 0], pairs[:, 1]
        keep = (duplicate != original) & ~landmarks.bad[original]  # an original retired meanwhile replaces nothing
        duplicate, original = duplicate[keep], original[keep]
        if not len(duplicate):
            return
        replace = np.arange(len(landmarks))
        replace[duplicate] = original
        while np.any(replace[replace] != replace):  # a duplicate that is also another pair's original: follow on
            replace = replace[replace]
        for keyframe in self.map.keyframes:
            seen = keyframe.landmark_ids >= 0
            keyframe.landmark_ids[seen] = replace[keyframe.landmark_ids[seen]]
        landmarks.bad[duplicate] = True


def optimise_pose_graph(poses_wc: np.ndarray, candidate: int, keyframe: int, corrected_wc: np.ndarray,
                        conf: LoopClosingConfig, joined: np.ndarray | None = None) -> np.ndarray:
    """Camera-to-world poses after a pose graph (gtsam, Levenberg-Marquardt) over the chain of keyframes, each edge
    its current relative pose, plus the loop edge candidate -> keyframe at ``corrected_wc``; the first keyframe
    is held. ``joined`` (K,) False where a keyframe is not joined to the one before by the map (a new start after
    a loss): that edge is a loose guess (``unjoined_sigma_m``, ``unjoined_sigma_rad``)."""
    import gtsam  # noqa: PLC0415 - imported where needed: the per-frame path does not load it

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for i, pose in enumerate(poses_wc):
        values.insert(i, gtsam.Pose3(pose))
    held = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
    chain = gtsam.noiseModel.Diagonal.Sigmas(np.array([conf.chain_sigma_rad] * 3 + [conf.chain_sigma_m] * 3))
    closing = gtsam.noiseModel.Diagonal.Sigmas(np.array([conf.loop_sigma_rad] * 3 + [conf.loop_sigma_m] * 3))
    loose = gtsam.noiseModel.Diagonal.Sigmas(np.array([conf.unjoined_sigma_rad] * 3 + [conf.unjoined_sigma_m] * 3))
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(poses_wc[0]), held))
    for i in range(1, len(poses_wc)):
        step = gtsam.Pose3(invert_pose(poses_wc[i - 1]) @ poses_wc[i])
        graph.add(gtsam.BetweenFactorPose3(i - 1, i, step, chain if joined is None or joined[i] else loose))
    graph.add(gtsam.BetweenFactorPose3(candidate, keyframe,
                                       gtsam.Pose3(invert_pose(poses_wc[candidate]) @ corrected_wc), closing))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    return np.stack([result.atPose3(i).matrix() for i in range(len(poses_wc))])
