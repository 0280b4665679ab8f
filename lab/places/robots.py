"""Can one robot's keyframes be found in another robot's map? An offline study for co-mapping (one map built by
several robots, merged when they recognise each other's places).

Two robots' maps are built in process (``twohr run``'s pipeline): robot a on one stretch of a sequence, robot b on
another (the backwards variant, say, so that b walks over ground a has mapped). Then each of b's keyframes, in the
order b made them, is looked for in a's map as the loop closer looks for an older place in its own:

- **Candidates** from a bag of words built *online* from a's own keyframes (k-means over their landmarks'
  descriptors: no training data shipped), a's keyframes ranked by cosine against b's keyframe;
- **verified** by :func:`twohr.places.verify`: descriptor matches, RANSAC PnP of b's keypoints on a's
  landmarks, the pose refined with depth, and the loop closer's view-change gate;
- each verified match gives one transform of b's map frame into a's; **a merge** needs ``k`` of them that agree
  (within ``agree_m`` and ``agree_deg`` of their median).

Against the ground truth (each map's frame placed in the ground truth's by its poses, 0.02 s association), every
match is scored by how far its transform puts b's keyframe from where it truly is in a's frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twohr.config import PipelineConfig
from twohr.geometry import invert_pose, rotation_angle
from twohr.places import LoopCandidate, LoopQuery, PlaceIndex, Vocabulary, verify
from twohr.trajectory import Trajectory
from twohr_services.tracker.map import Map

#: words of the vocabulary built from a robot's keyframes (a room's map has tens to hundreds of keyframes)
ONLINE_WORDS = 128


@dataclass
class CrossMatch:
    """One of b's keyframes found in a's map: against which of a's keyframes, with how many inliers, and the
    transform of b's map frame into a's that it gives (``T_ab``: b's map coordinates to a's)."""

    b_keyframe: int
    b_stamp: float
    a_keyframe: int
    inliers: int
    T_ab: np.ndarray


def _observed(world: Map, keyframe_id: int) -> np.ndarray:
    """Keypoint indices of a keyframe that observe a described, usable landmark."""
    ids = world.keyframes[keyframe_id].landmark_ids
    usable = ids >= 0
    usable[usable] = ~world.landmarks.bad[ids[usable]] & world.landmarks.described[ids[usable]]
    return np.flatnonzero(usable)


def _descriptors(world: Map, keyframe_id: int) -> np.ndarray:
    return world.landmarks.descriptors[world.keyframes[keyframe_id].landmark_ids[_observed(world, keyframe_id)]]


def online_vocabulary(world: Map, words: int = ONLINE_WORDS) -> Vocabulary:
    """A vocabulary from a map's own keyframes (each keyframe one document)."""
    sets = [_descriptors(world, k.id) for k in world.keyframes if not k.culled]
    return Vocabulary.train([s for s in sets if len(s)], words, card={"name": "online", "trained_on": "the map"})


def cross_matches(map_a: Map, map_b: Map, K: np.ndarray, config: PipelineConfig, match,
                  candidates: int = 3) -> list[CrossMatch]:
    """Each of b's keyframes looked for in a's map (see the module docstring; ``K``: b's camera matrix, whose
    keypoints are fitted to a's landmarks); the verified ones, in b's order."""
    conf, tracking = config.loop_closing, config.tracker
    vocabulary = online_vocabulary(map_a)
    index = PlaceIndex(vocabulary.size)
    for keyframe in map_a.keyframes:
        if not keyframe.culled and len(_observed(map_a, keyframe.id)):
            index.add(keyframe.id, vocabulary.vector(_descriptors(map_a, keyframe.id)))
    found = []
    for keyframe in map_b.keyframes:
        observed = _observed(map_b, keyframe.id)
        if keyframe.culled or len(observed) < conf.min_inliers:
            continue
        ids = keyframe.landmark_ids[observed]
        vector = vocabulary.vector(map_b.landmarks.descriptors[ids])
        chosen = []
        for candidate_id, score in index.search(vector, candidates, lambda _k: True):
            span = range(max(0, candidate_id - conf.candidate_neighbours),
                         min(len(map_a.keyframes), candidate_id + conf.candidate_neighbours + 1))
            neighbours = np.array([k for k in span if not map_a.keyframes[k].culled], np.int64)
            landmarks = map_a.usable_landmarks(neighbours, described=True)
            if len(landmarks) >= conf.min_inliers:
                chosen.append(LoopCandidate(candidate_id, score, landmarks, map_a.landmarks.positions[landmarks],
                                            map_a.landmarks.descriptors[landmarks],
                                            map_a.keyframe_poses[candidate_id]))
        if not chosen:
            continue
        query = LoopQuery(keyframe.id, keyframe.stamp, keyframe.xy[observed], keyframe.depth[observed], ids,
                          map_b.landmarks.descriptors[ids], chosen)
        verdict = verify(query, K, conf, tracking, match)
        if verdict.loop is None:
            continue
        loop = verdict.loop
        T_a_keyframe = map_a.keyframe_poses[loop.candidate_id] @ loop.relative  # b's keyframe, in a's frame
        found.append(CrossMatch(keyframe.id, keyframe.stamp, loop.candidate_id, len(loop.pairs),
                                T_a_keyframe @ invert_pose(map_b.keyframe_poses[keyframe.id])))
    return found


def pose_gap(T_1: np.ndarray, T_2: np.ndarray) -> tuple[float, float]:
    """(metres, degrees) between two poses."""
    delta = invert_pose(T_1) @ T_2
    return float(np.linalg.norm(delta[:3, 3])), float(np.degrees(rotation_angle(delta[:3, :3])))


def consistent_merge(matches: list[CrossMatch], k: int = 3, agree_m: float = 0.1,
                     agree_deg: float = 5.0) -> tuple[int, np.ndarray] | None:
    """The first point in ``matches`` at which ``k`` of the matches so far give transforms within ``agree_m`` and
    ``agree_deg`` of one of them: (the index of the match that completed them, that match's transform); None if
    never."""
    for end in range(len(matches)):
        seen = matches[:end + 1]
        for centre in seen:
            close = [m for m in seen if all(gap <= limit for gap, limit in zip(
                pose_gap(centre.T_ab, m.T_ab), (agree_m, agree_deg), strict=True))]
            if len(close) >= k:
                return end, centre.T_ab
    return None


def map_to_world(estimate: Trajectory, truth: Trajectory, max_dt: float = 0.02) -> np.ndarray:
    """The SE(3) transform of an estimated trajectory's frame into the ground truth's: the mean of ``G_i E_i^-1``
    over the associated poses (rotations by their chordal mean). From whole poses, not positions alone: a short,
    nearly straight path leaves a positions-only (Umeyama) rotation loose by degrees."""
    from twohr.evaluation import associate_trajectories
    from twohr.geometry import nearest_rotation

    gt, est = associate_trajectories(truth, estimate, max_dt)
    each = gt.poses @ np.linalg.inv(est.poses)
    T = np.eye(4)
    T[:3, :3] = nearest_rotation(each[:, :3, :3].sum(axis=0))
    T[:3, 3] = each[:, :3, 3].mean(axis=0)
    return T


def true_T_ab(trajectory_a: Trajectory, truth_a: Trajectory, trajectory_b: Trajectory,
              truth_b: Trajectory) -> np.ndarray:
    """b's map frame into a's, as the ground truth has it (both aligned to the same world)."""
    return invert_pose(map_to_world(trajectory_a, truth_a)) @ map_to_world(trajectory_b, truth_b)


def score_matches(matches: list[CrossMatch], map_b: Map, T_ab_true: np.ndarray) -> list[tuple[float, float]]:
    """For each match, (metres, degrees) between where its transform puts b's keyframe in a's frame and where the
    ground truth does."""
    return [pose_gap(m.T_ab @ map_b.keyframe_poses[m.b_keyframe], T_ab_true @ map_b.keyframe_poses[m.b_keyframe])
            for m in matches]
