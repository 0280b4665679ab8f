"""The map: landmarks, keyframes and the only copy of the keyframe poses, with local and final bundle adjustment.

Plain arrays and integer ids, nothing that refers to a thread, a session or a tracker, so that a map can be
copied into a snapshot for the per-frame path (:meth:`Map.snapshot`) and, later, saved and loaded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from twohr.config import TrackerConfig
from twohr.dataset import CameraIntrinsics
from twohr.geometry import invert_pose, transform_points
from twohr.mapfile import MapArrays

from .bundle_adjustment import bundle_adjust

#: a retired landmark's row is offered for reuse this many keyframes after it was first seen idle: a job that
#: started before it was retired (a 2HR keyframe, a description) has come back by then
REUSE_AFTER_KEYFRAMES = 2


@dataclass
class Keyframe:
    """A frame kept in the map: its keypoints with depth and the landmark each one observes (-1 = none). Its pose
    is row ``id`` of :attr:`Map.keyframe_poses`. Descriptors are the landmarks' (:class:`Landmarks`): a keyframe
    holds none of its own, they would be most of the map's memory and nothing reads them."""

    id: int
    stamp: float
    xy: np.ndarray
    depth: np.ndarray
    landmark_ids: np.ndarray
    culled: bool = False
    """redundant, so its observations and keypoints were dropped (:meth:`Map.cull_redundant`)"""


class Landmarks:
    """3-D landmarks in growable arrays: world positions, one descriptor each, and vote counts.

    A landmark seeded from a corner on a tracked keyframe has no descriptor until a 2HR detection of a keyframe
    that observes it gives it one (``described``); until then only optical flow and bundle adjustment use it.
    The rows of retired landmarks that nothing refers to any more are filled again by new ones (:attr:`free`,
    :meth:`Map.reuse_rows`), so a camera that keeps coming back to the same places keeps its arrays bounded."""

    def __init__(self) -> None:
        self.positions = np.zeros((0, 3))
        self.descriptors: np.ndarray | None = None
        self.described = np.zeros(0, bool)
        self.accepted = np.zeros(0, np.int64)
        self.rejected = np.zeros(0, np.int64)
        self.bad = np.zeros(0, bool)
        self.free = np.zeros(0, np.int64)
        """rows of retired landmarks that :meth:`add` fills before it grows the arrays"""
        self.made = 0
        """landmarks ever added (rows filled again count again)"""
        self.born = np.zeros(0, np.int64)
        """(L,) each landmark's place in the order landmarks were made (a row filled again is younger than its id)"""

    def __len__(self) -> int:
        return len(self.positions)

    @property
    def num_good(self) -> int:
        return int((~self.bad).sum())

    def add(self, positions: np.ndarray, descriptors: np.ndarray | None = None) -> np.ndarray:
        """Add landmarks, in free rows first (``descriptors`` None: not described yet, needs landmarks with
        descriptors before it); returns their ids."""
        count = len(positions)
        described = descriptors is not None
        if descriptors is None:
            if self.descriptors is None:
                raise ValueError("the first landmarks of a map need descriptors")
            descriptors = np.zeros((count, self.descriptors.shape[1]), self.descriptors.dtype)
        reused, self.free = self.free[:count], self.free[count:]
        start, grow = len(self), count - len(reused)
        self.positions = np.concatenate([self.positions, np.zeros((grow, 3))])
        self.descriptors = (np.zeros((grow, descriptors.shape[1]), descriptors.dtype) if self.descriptors is None
                            else np.concatenate([self.descriptors, np.zeros((grow, self.descriptors.shape[1]),
                                                                            self.descriptors.dtype)]))
        self.described = np.concatenate([self.described, np.zeros(grow, bool)])
        self.accepted = np.concatenate([self.accepted, np.zeros(grow, np.int64)])
        self.rejected = np.concatenate([self.rejected, np.zeros(grow, np.int64)])
        self.bad = np.concatenate([self.bad, np.zeros(grow, bool)])
        self.born = np.concatenate([self.born, np.zeros(grow, np.int64)])
        ids = np.concatenate([reused, np.arange(start, start + grow)])
        self.positions[ids] = positions
        self.descriptors[ids] = descriptors
        self.described[ids] = described
        self.accepted[ids] = 0
        self.rejected[ids] = 0
        self.bad[ids] = False
        self.born[ids] = self.made + np.arange(count)
        self.made += count
        return ids

    def most_accepted(self, ids: np.ndarray) -> np.ndarray:
        """``ids`` ordered by their accepted matches, most first; among equals the older first (so that filled rows
        do not change which landmarks come first)."""
        ids = np.asarray(ids, np.int64)
        return ids[np.lexsort((self.born[ids], -self.accepted[ids]))]

    def describe(self, ids: np.ndarray, descriptors: np.ndarray) -> None:
        """Give landmarks ``ids`` their descriptors (from a 2HR keypoint observing them)."""
        self.descriptors[ids] = descriptors
        self.described[ids] = True

    def vote(self, accepted: np.ndarray, rejected: np.ndarray, max_outlier_ratio: float) -> None:
        """Count matches that agreed / disagreed with the tracked pose; retire landmarks that mostly disagree
        (moving objects that slipped past the mask, or repeated texture)."""
        np.add.at(self.accepted, accepted, 1)
        np.add.at(self.rejected, rejected, 1)
        ids = np.unique(rejected)
        self.bad[ids] |= (self.rejected[ids] >= 3) & (self.rejected[ids] > max_outlier_ratio * self.accepted[ids])


@dataclass
class MapSnapshot:
    """A read-only copy of what the per-frame path needs of the map, as of its ``version`` (:attr:`Map.version`)."""

    version: int
    landmark_positions: np.ndarray
    """(L, 3) every landmark's world position"""
    landmark_usable: np.ndarray
    """(L,) False for landmarks retired as outliers"""
    keyframe_poses: np.ndarray
    """(K, 4, 4) camera-to-world poses of all keyframes"""
    keyframe_stamps: np.ndarray
    """(K,) the keyframes' frame stamps"""

    @classmethod
    def empty(cls) -> MapSnapshot:
        return cls(0, np.zeros((0, 3)), np.zeros(0, bool), np.zeros((0, 4, 4)), np.zeros(0))

    @property
    def points(self) -> np.ndarray:
        """(N, 3) world positions of the usable landmarks."""
        return self.landmark_positions[self.landmark_usable]


class Map:
    """Landmarks and keyframes of one camera's map. Keyframe poses change only when a keyframe is added, when
    :meth:`local_bundle_adjustment` or :meth:`final_bundle_adjustment` refine them, and when a loop is closed
    (:meth:`~.loops.LoopClosing.close`)."""

    def __init__(self, camera: CameraIntrinsics, conf: TrackerConfig) -> None:
        self.camera = camera
        self.conf = conf
        self.K = camera.matrix
        self.landmarks = Landmarks()
        self.keyframes: list[Keyframe] = []
        self.keyframe_poses = np.zeros((0, 4, 4))
        """(K, 4, 4) camera-to-world poses of the keyframes, as bundle adjustment has refined them"""
        self.corrections = 0
        """loops closed: each moved the whole map"""
        self._unconfirmed: list[tuple[int, np.ndarray]] = []
        """(keyframe count when made, landmark ids) of new landmarks not yet judged by :meth:`retire_unconfirmed`"""
        self._idle_since = np.zeros(0, np.int64)
        """(L,) the keyframe count when each landmark was first seen retired and unobserved (-1: it is not)"""

    def __bool__(self) -> bool:
        return bool(self.keyframes)

    @property
    def version(self) -> int:
        """Changes when the map does (a keyframe was added, a loop closed)."""
        return len(self.keyframes) + self.corrections

    def snapshot(self) -> MapSnapshot:
        """A copy of the landmark positions and keyframe poses, for a reader on another thread."""
        return MapSnapshot(self.version, self.landmarks.positions.copy(), ~self.landmarks.bad,
                           self.keyframe_poses.copy(), np.array([kf.stamp for kf in self.keyframes]))

    def add_keyframe(self, stamp: float, pose: np.ndarray, xy: np.ndarray, depth: np.ndarray,
                     landmark_ids: np.ndarray) -> Keyframe:
        """Keep a frame at camera-to-world ``pose``, observing ``landmark_ids`` (-1 = none) with its keypoints."""
        keyframe = Keyframe(len(self.keyframes), stamp, xy, depth, landmark_ids)
        self.keyframes.append(keyframe)
        self.keyframe_poses = np.concatenate([self.keyframe_poses, pose[None]])
        return keyframe

    def arrays(self) -> MapArrays:
        """The map as the arrays of a map file (:mod:`twohr.mapfile`)."""
        keyframes, landmarks = self.keyframes, self.landmarks
        first = np.cumsum([0] + [len(kf.landmark_ids) for kf in keyframes]).astype(np.int64)
        descriptors = landmarks.descriptors if landmarks.descriptors is not None else np.zeros((0, 1), np.float32)

        def joined(parts: list[np.ndarray], shape: tuple[int, ...], dtype) -> np.ndarray:
            return np.concatenate(parts).astype(dtype) if parts else np.zeros(shape, dtype)

        return MapArrays(
            keyframe_poses=self.keyframe_poses.copy(), keyframe_stamps=np.array([kf.stamp for kf in keyframes]),
            keyframe_culled=np.array([kf.culled for kf in keyframes], bool), keyframe_first=first,
            keypoint_xy=joined([kf.xy for kf in keyframes], (0, 2), np.float32),
            keypoint_depth=joined([kf.depth for kf in keyframes], (0,), np.float32),
            keypoint_landmark=joined([kf.landmark_ids for kf in keyframes], (0,), np.int64),
            landmark_positions=landmarks.positions.copy(), landmark_descriptors=descriptors.copy(),
            landmark_accepted=landmarks.accepted.copy(), landmark_rejected=landmarks.rejected.copy(),
            landmark_bad=landmarks.bad.copy())

    @classmethod
    def from_arrays(cls, camera: CameraIntrinsics, conf: TrackerConfig, arrays: MapArrays) -> Map:
        """A map from the arrays of a map file (checked by :func:`twohr.mapfile.read_map`)."""
        world = cls(camera, conf)
        landmarks = world.landmarks
        landmarks.positions = arrays.landmark_positions.astype(np.float64)
        landmarks.descriptors = arrays.landmark_descriptors
        landmarks.described = np.any(arrays.landmark_descriptors != 0, axis=1)  # stored as zeros
        landmarks.accepted = arrays.landmark_accepted.astype(np.int64)
        landmarks.rejected = arrays.landmark_rejected.astype(np.int64)
        landmarks.bad = arrays.landmark_bad.astype(bool)
        landmarks.made = len(landmarks)
        landmarks.born = np.arange(len(landmarks))
        first = arrays.keyframe_first
        for k in range(len(arrays.keyframe_stamps)):
            part = slice(first[k], first[k + 1])
            world.keyframes.append(Keyframe(k, float(arrays.keyframe_stamps[k]),
                                            arrays.keypoint_xy[part].astype(np.float64),
                                            arrays.keypoint_depth[part].astype(np.float64),
                                            arrays.keypoint_landmark[part].astype(np.int64),
                                            culled=bool(arrays.keyframe_culled[k])))
        world.keyframe_poses = arrays.keyframe_poses.astype(np.float64).reshape(-1, 4, 4)
        return world

    def local_keyframes(self, pose: np.ndarray, count: int) -> np.ndarray:
        """Indices of the latest keyframe and the keyframes nearest to ``pose`` (translation + weighted angle)."""
        rel = np.einsum("ij,njk->nik", invert_pose(pose), self.keyframe_poses)
        cos = np.clip((np.trace(rel[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)
        distance = np.linalg.norm(rel[:, :3, 3], axis=1) + self.conf.keyframe_distance_per_rad * np.arccos(cos)
        distance[[kf.culled for kf in self.keyframes]] = np.inf  # they observe nothing any more
        distance[-1] = -1.0  # always keep the latest keyframe
        order = np.argsort(distance, kind="stable")[:count]
        return order[np.isfinite(distance[order])]

    def cull_redundant(self, candidates: np.ndarray) -> list[int]:
        """Cull the keyframes among ``candidates`` (indices; never the first keyframe, nor one of the latest
        ``ba_window_keyframes``) whose usable landmarks are at least a ``keyframe_culling`` share observed by three
        other keyframes as well: they add nothing the others do not (ORB-SLAM3's local mapping culls such keyframes).
        A culled keyframe's observations and keypoints are dropped; its pose stays, frozen, as the
        anchor of the frames recorded against it. Returns the culled indices."""
        share = self.conf.keyframe_culling
        if share <= 0 or len(self.keyframes) <= self.conf.ba_window_keyframes + 1:
            return []
        observers = self.observers()
        newest_protected = len(self.keyframes) - self.conf.ba_window_keyframes
        culled = []
        for i in sorted(int(c) for c in candidates):
            keyframe = self.keyframes[i]
            if i == 0 or i >= newest_protected or keyframe.culled:
                continue
            ids = keyframe.landmark_ids[keyframe.landmark_ids >= 0]
            ids = ids[~self.landmarks.bad[ids]]
            if len(ids) == 0 or np.mean(observers[ids] >= 4) < share:  # itself and three others
                continue
            observers[keyframe.landmark_ids[keyframe.landmark_ids >= 0]] -= 1
            self.keyframes[i] = Keyframe(keyframe.id, keyframe.stamp, np.zeros((0, 2)), np.zeros(0),
                                         np.zeros(0, np.int64), culled=True)
            culled.append(i)
        return culled

    def observers(self) -> np.ndarray:
        """(L,) how many keyframes observe each landmark."""
        return np.bincount(np.concatenate([np.zeros(0, np.int64), *(kf.landmark_ids[kf.landmark_ids >= 0]
                                                                   for kf in self.keyframes)]),
                           minlength=len(self.landmarks))

    def made_landmarks(self, ids: np.ndarray) -> None:
        """Note landmarks just made, for :meth:`retire_unconfirmed` to judge two keyframes later."""
        if len(ids):
            self._unconfirmed.append((len(self.keyframes), np.asarray(ids, np.int64)))

    def retire_unconfirmed(self) -> np.ndarray:
        """Retire the landmarks made two or more keyframes ago that no keyframe but one observes: no later view
        found them again, so they constrain no pose and only hold the map's keyframes apart (ORB-SLAM3's map-point
        culling for RGB-D, which lets :meth:`cull_redundant` find the keyframes a revisit made redundant). Returns
        the retired ids."""
        due = [ids for made, ids in self._unconfirmed if len(self.keyframes) - made >= 2]
        self._unconfirmed = [(made, ids) for made, ids in self._unconfirmed if len(self.keyframes) - made < 2]
        if not due:
            return np.zeros(0, np.int64)
        ids = np.concatenate(due)
        observers = self.observers()
        lonely = ids[(observers[ids] < 2) & ~self.landmarks.bad[ids]]
        self.landmarks.bad[lonely] = True
        return lonely

    def idle_rows(self) -> np.ndarray:
        """Rows of landmarks retired, observed by no keyframe and awaiting no judgement for at least
        :data:`REUSE_AFTER_KEYFRAMES` keyframes, not free yet: no map structure refers to them. The per-frame
        path, which may still hold some (its tracks, the frames kept for refinement), gives the others back
        (:meth:`reuse_rows`)."""
        return np.flatnonzero(self._idle())

    def reuse_rows(self, ids: np.ndarray) -> None:
        """Let new landmarks fill rows ``ids`` (from :meth:`idle_rows`, which nothing else holds any more); each is
        checked again, so a row that is no longer idle is left alone."""
        ids = np.unique(np.asarray(ids, np.int64))
        ids = ids[(ids >= 0) & (ids < len(self.landmarks))]
        ids = ids[self._idle()[ids]]
        self.landmarks.free = np.concatenate([self.landmarks.free, ids])

    def _idle(self) -> np.ndarray:
        landmarks = self.landmarks
        idle = landmarks.bad & (self.observers() == 0)
        idle[landmarks.free] = False
        for _, ids in self._unconfirmed:
            idle[ids] = False
        since = np.concatenate([self._idle_since[:len(idle)], np.full(len(idle) - len(self._idle_since), -1)])
        since[~idle] = -1
        since[idle & (since < 0)] = len(self.keyframes)
        self._idle_since = since
        return idle & (len(self.keyframes) - since >= REUSE_AFTER_KEYFRAMES)

    def working_set(self) -> dict[str, int]:
        """How much of the map tracking still works with: keyframes inserted, culled and live, and landmarks made,
        those live keyframes observe, and the rows the landmarks take (culled keyframes keep only their pose, for the
        frames kept against it; retired landmarks' rows are filled again)."""
        live = [kf for kf in self.keyframes if not kf.culled]
        observed = np.unique(np.concatenate([kf.landmark_ids for kf in live])) if live else np.zeros(0, np.int64)
        observed = observed[observed >= 0]
        return {"keyframes": len(self.keyframes), "culled": len(self.keyframes) - len(live),
                "live_keyframes": len(live), "landmarks": self.landmarks.made,
                "live_landmarks": int((~self.landmarks.bad[observed]).sum()), "landmark_rows": len(self.landmarks)}

    def usable_landmarks(self, keyframe_indices: np.ndarray, described: bool = False) -> np.ndarray:
        """Sorted ids of the landmarks that keyframes ``keyframe_indices`` observe, retired ones left out (and those
        without a descriptor, with ``described``: what descriptor matching can use)."""
        ids = np.unique(np.concatenate([self.keyframes[i].landmark_ids for i in keyframe_indices]))
        ids = ids[ids >= 0]
        keep = ~self.landmarks.bad[ids]
        if described:
            keep &= self.landmarks.described[ids]
        return ids[keep]

    # ------------------------------------------------------------------ bundle adjustment

    def local_bundle_adjustment(self) -> None:
        """Refine the latest keyframes and the landmarks they share; keyframes outside the window that see
        those landmarks are held fixed."""
        window = np.arange(max(0, len(self.keyframes) - self.conf.ba_window_keyframes), len(self.keyframes))
        self.bundle_adjust(window, self.conf.ba_max_iterations)

    def final_bundle_adjustment(self) -> None:
        """Bundle adjustment over every keyframe (at most ``final_ba_max_keyframes`` latest) and the landmarks
        they see, for the end of a run (``final_ba_iterations``; 0 = off)."""
        conf = self.conf
        if conf.final_ba_iterations > 0:
            first = max(0, len(self.keyframes) - conf.final_ba_max_keyframes)
            self.bundle_adjust(np.arange(first, len(self.keyframes)), conf.final_ba_iterations)

    def bundle_adjust(self, window: np.ndarray, iterations: int) -> None:
        """Refine the keyframes in ``window`` and the landmarks they see; other keyframes that see those
        landmarks are held fixed, and so is the oldest keyframe of any part of the map that has none held (the
        gauge). Landmarks seen only once move rigidly with their keyframe, and outlying observations are cut
        from their keyframe."""
        conf = self.conf
        landmarks = self.landmarks
        if len(self.keyframes) < 2:
            return
        in_window = np.zeros(len(landmarks), bool)
        for i in window:
            ids = self.keyframes[i].landmark_ids
            in_window[ids[ids >= 0]] = True
        in_window &= ~landmarks.bad
        frame_parts, keypoint_parts = [], []  # (keyframe index, keypoint index) of every observation
        for i, kf in enumerate(self.keyframes):
            seen = np.flatnonzero((kf.landmark_ids >= 0) & in_window[np.maximum(kf.landmark_ids, 0)])
            frame_parts.append(np.full(len(seen), i))
            keypoint_parts.append(seen)
        obs_frame, obs_keypoint = np.concatenate(frame_parts), np.concatenate(keypoint_parts)
        obs_landmark = np.concatenate([self.keyframes[i].landmark_ids[k] for i, k in
                                       zip(range(len(self.keyframes)), keypoint_parts, strict=True)])
        seen_twice = np.bincount(obs_landmark, minlength=len(landmarks)) >= 2
        keep = seen_twice[obs_landmark]  # a landmark seen once constrains no pose
        obs_frame, obs_keypoint, obs_landmark = obs_frame[keep], obs_keypoint[keep], obs_landmark[keep]
        if len(obs_frame) == 0:
            return
        used_frames, obs_pose = np.unique(obs_frame, return_inverse=True)
        landmark_ids, obs_point = np.unique(obs_landmark, return_inverse=True)
        fixed = hold_gauge(~np.isin(used_frames, window), obs_pose, obs_point)
        xy = np.concatenate([self.keyframes[f].xy[obs_keypoint[obs_frame == f]] for f in used_frames])
        depth = np.concatenate([self.keyframes[f].depth[obs_keypoint[obs_frame == f]] for f in used_frames])
        order = np.argsort(obs_frame, kind="stable")  # xy and depth were gathered frame by frame
        obs_pose, obs_point, obs_frame, obs_keypoint = obs_pose[order], obs_point[order], obs_frame[order], \
            obs_keypoint[order]
        poses_cw = invert_pose(self.keyframe_poses[used_frames])
        result = bundle_adjust(self.K, poses_cw, landmarks.positions[landmark_ids], obs_pose, obs_point, xy, depth,
                               fixed, conf.depth_noise, conf.huber_px, iterations,
                               outlier_threshold=2 * conf.ransac_reprojection_px)
        landmarks.positions[landmark_ids] = result.points_w
        for j, f in enumerate(used_frames):
            if fixed[j]:
                continue
            kf = self.keyframes[f]
            new_pose = invert_pose(result.poses_cw[j])
            alone = kf.landmark_ids[(kf.landmark_ids >= 0)]
            alone = alone[~seen_twice[alone]]
            landmarks.positions[alone] = transform_points(new_pose @ invert_pose(self.keyframe_poses[f]),
                                                          landmarks.positions[alone])
            self.keyframe_poses[f] = new_pose
        for f in np.unique(obs_frame[result.outliers]):
            cut = obs_keypoint[result.outliers & (obs_frame == f)]
            self.keyframes[f].landmark_ids[cut] = -1


def hold_gauge(fixed: np.ndarray, obs_pose: np.ndarray, obs_point: np.ndarray) -> np.ndarray:
    """``fixed`` (P,) with the first pose of every connected part of the problem held where that part holds
    none: poses joined by shared points form a part, and a part with nothing fixed could drift freely (a map
    restarted after a long loss shares no landmark with the one before)."""
    n_poses = len(fixed)
    n_nodes = n_poses + int(obs_point.max()) + 1
    graph = coo_matrix((np.ones(len(obs_pose)), (obs_pose, n_poses + obs_point)), shape=(n_nodes, n_nodes))
    _, part = connected_components(graph, directed=False)
    fixed = fixed.copy()
    for label in np.unique(part[:n_poses]):
        members = np.flatnonzero(part[:n_poses] == label)
        if not fixed[members].any():
            fixed[members[0]] = True
    return fixed
