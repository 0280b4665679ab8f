"""One map built by many robots at once: the map server's core (arrays in, events out; no bus).

Each robot in a session that shares map ``lab`` sends its keyframes as it makes them (:class:`KeyframeBatch`). The
core keeps one :class:`Submap` per robot, in the robot's own frame. The first robot's frame is the map's (or, where
the map was stored before, the stored map's). Every other robot's new keyframes are looked for among the keyframes
of the robots already in the map's frame:

- **candidates** come from a bag of words built online from the map's own keyframes (k-means over their landmarks'
  descriptors, :data:`ONLINE_WORDS` words, built again each time the map doubled): no vocabulary trained
  on other images ships with the product;
- each candidate is **verified** as the loop closer verifies a loop (:func:`twohr.places.verify`: descriptor
  matches, RANSAC PnP of the keyframe's keypoints on the candidate's landmarks, the pose refined with depth, the
  view-change gate);
- a verified match gives one transform of the robot's frame into the map's (:class:`CrossMatch`); ``k`` of them
  that agree (:func:`consistent_merge`) **merge** the robot: its transform is their mean, and a
  :class:`MergeEvent` says so.

A keyframe keeps its points in its own camera frame, so a keyframe pose moved by the robot's bundle adjustment or
loop closing (every batch carries all its keyframes' poses) carries its points along.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from twohr.config import LoopClosingConfig, TrackerConfig
from twohr.dataset import CameraIntrinsics
from twohr.geometry import invert_pose, nearest_rotation, rotation_angle, transform_points
from twohr.keyframe_sender import KeyframeSender
from twohr.mapfile import MapArrays, MapFile
from twohr.places import MatchFn, PlaceCandidate, PlaceIndex, PlaceQuery, Vocabulary, VocabularyError, verify

#: words of the vocabulary built from the map's own keyframes (a room's map has tens to hundreds of keyframes)
ONLINE_WORDS = 128
#: descriptors the online vocabulary is trained on at most (an even sample of the map's): k-means stays ~0.1 s
VOCABULARY_SAMPLE = 6_000
#: the map is searched once it has this many keyframes (fewer make too few words)
MIN_MAP_KEYFRAMES = 4
#: a new vocabulary once the map has this many times the keyframes it was built from
REBUILD_GROWTH = 2.0
#: a merged robot's transform is refined by its later matches until this many agree
REFINE_MATCHES = 5
#: once merged, every this-many-th keyframe of the robot is searched (the search's RANSAC PnP is most of the map
#: server's CPU, on cores the robots' trackers need)
REFINE_EVERY = 2
#: the best places by bag of words that are verified for one keyframe
CANDIDATES = 2
#: and said again when the refinement moves it this far
REFINE_MOVE_M = 0.003
REFINE_MOVE_DEG = 0.15
#: a robot's landmark and the stored map's landmark of the same row are one where they lie this close (m)
FUSE_M = 0.1
#: the submap of the stored map a shared map started from (no robot id is empty)
STORED = ""


@dataclass
class KeyframeBatch:
    """What a robot's tracker sends (:class:`twohr.messages.KeyframesMsg`), as arrays: every keyframe's pose
    (``poses`` (K, 4, 4) camera-to-world in the robot's frame, ``stamps`` (K,)), and for keyframes ``first`` on,
    their observations (``keypoint_first`` (n + 1,) splits ``xy`` (P, 2), ``depth`` (P,), ``landmark`` (P,),
    ``positions`` (P, 3) in the robot's frame), and the descriptors of landmarks ``described`` (M,) not sent
    before, ``descriptors`` (M, D)."""

    poses: np.ndarray
    stamps: np.ndarray
    first: int
    keypoint_first: np.ndarray
    xy: np.ndarray
    depth: np.ndarray
    landmark: np.ndarray
    positions: np.ndarray
    described: np.ndarray
    descriptors: np.ndarray


#: the most keyframe poses one batch may carry (every keyframe of the session so far: a long session has a few
#: thousand), keypoints and new descriptors (a batch's new keyframes see a few thousand)
MAX_BATCH_KEYFRAMES = 100_000
MAX_BATCH_POINTS = 2_000_000
#: how far a pose's rotation may be from a rotation (|R^T R - I|, max entry) and its last row from (0, 0, 0, 1)
RIGID_TOLERANCE = 1e-3


class BatchRefused(ValueError):
    """A robot's keyframe batch that does not fit its session: said in one line, never taken in part."""


def check_batch(batch: KeyframeBatch, descriptor_width: int, descriptor_dtype: str) -> None:
    """:class:`BatchRefused` unless ``batch`` is what a tracker sends (:class:`KeyframeBatch`): K×4×4 finite rigid
    poses and K finite stamps, ``keypoint_first`` from 0 up to P for keyframes ``first`` on within the K, P rows of
    finite observations, landmark ids of 0 and above, and descriptors of the session's network (``descriptor_width``
    of ``descriptor_dtype``, known from its start, never from a batch), each array under the stated caps."""
    poses, stamps, starts = batch.poses, batch.stamps, batch.keypoint_first
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or stamps.shape != (len(poses),):
        raise BatchRefused(f"poses {poses.shape} and stamps {stamps.shape}: want (K, 4, 4) and (K,)")
    if len(poses) > MAX_BATCH_KEYFRAMES:
        raise BatchRefused(f"{len(poses)} keyframe poses: at most {MAX_BATCH_KEYFRAMES}")
    if not (np.isfinite(poses).all() and np.isfinite(stamps).all()):
        raise BatchRefused("poses or stamps that are not finite")
    rotations = poses[:, :3, :3].astype(np.float64)
    off_rotation = np.abs(np.einsum("kji,kjl->kil", rotations, rotations) - np.eye(3)).max(initial=0.0)
    off_row = np.abs(poses[:, 3, :] - (0, 0, 0, 1)).max(initial=0.0)
    if off_rotation > RIGID_TOLERANCE or off_row > RIGID_TOLERANCE or (np.linalg.det(rotations) < 0).any():
        raise BatchRefused("a pose that is not rigid")
    if starts.ndim != 1 or len(starts) < 1 or batch.first + len(starts) - 1 > len(poses) or not np.issubdtype(
            starts.dtype, np.integer):
        raise BatchRefused(f"keypoint_first {starts.shape} {starts.dtype} for keyframes {batch.first} on of "
                           f"{len(poses)}")
    points = len(batch.xy)
    if starts[0] != 0 or starts[-1] != points or (np.diff(starts) < 0).any():
        raise BatchRefused(f"keypoint_first does not split the {points} keypoints in order")
    if points > MAX_BATCH_POINTS or len(batch.described) > MAX_BATCH_POINTS:
        raise BatchRefused(f"{points} keypoints and {len(batch.described)} descriptors: at most {MAX_BATCH_POINTS}")
    shapes = {"xy": (batch.xy, (points, 2)), "depth": (batch.depth, (points,)),
              "landmark": (batch.landmark, (points,)), "positions": (batch.positions, (points, 3)),
              "described": (batch.described, (len(batch.described),)),
              "descriptors": (batch.descriptors, (len(batch.described), descriptor_width))}
    for name, (array, shape) in shapes.items():
        if array.shape != shape:
            raise BatchRefused(f"{name} {array.shape}: want {shape}")
    if batch.descriptors.dtype != np.dtype(descriptor_dtype):
        raise BatchRefused(f"descriptors of {batch.descriptors.dtype}: the session's network gives {descriptor_dtype}")
    for name in ("landmark", "described"):
        array = getattr(batch, name)
        if not np.issubdtype(array.dtype, np.integer) or (array < 0).any():
            raise BatchRefused(f"{name}: want landmark ids of 0 and above")
    if not all(np.isfinite(a).all() for a in (batch.xy, batch.depth, batch.positions, batch.descriptors)):
        raise BatchRefused("observations or descriptors that are not finite")


@dataclass
class Observations:
    """One keyframe's keypoints that observe a described landmark: pixel ``xy``, ``depth`` (m), the robot's
    ``landmark`` ids, the landmarks' ``points`` in the keyframe's camera frame, and their ``descriptors``."""

    xy: np.ndarray
    depth: np.ndarray
    landmark: np.ndarray
    points: np.ndarray
    descriptors: np.ndarray


@dataclass
class CrossMatch:
    """One of a robot's keyframes found among the map's: against which robot's keyframe, with how many inliers,
    and the transform of the robot's frame into the map's that it gives (``T_map_robot``)."""

    keyframe: int
    stamp: float
    into: str
    candidate: int
    inliers: int
    T_map_robot: np.ndarray
    pairs: np.ndarray
    """(M, 2) the inliers' landmark ids: (this robot's, the other robot's)"""
    relative: np.ndarray
    """the keyframe's camera-to-world pose in the other keyframe's frame, as verified"""


@dataclass
class MergeEvent:
    """A robot placed in the map's frame: ``kind`` ``merged`` (found by its places), ``defines`` (its frame is the
    map's), ``joined`` (it tracks in the stored map) or ``refined`` (a merged robot's transform moved by its later
    matches); ``T`` its frame into the map's."""

    robot: str
    session: str
    kind: str
    T: np.ndarray
    matches: list[CrossMatch] = field(default_factory=list)
    keyframes: int = 0
    stamp: float = 0.0
    ms: float = 0.0


class Submap:
    """One robot's keyframes in its own frame; ``T`` (None until merged) takes them into the map's frame.
    ``camera``: the robot's (None until its first keyframes came). Its keyframes are numbered from its first sent
    one: a robot that tracks in the stored map sends none of the stored map's keyframes (``offset`` of them)."""

    def __init__(self, robot: str, session: str, camera: CameraIntrinsics | None = None) -> None:
        self.robot, self.session, self.camera = robot, session, camera
        self.offset = 0
        self.all_poses = np.zeros((0, 4, 4))
        self.all_stamps = np.zeros(0)
        self.observations: list[Observations] = []
        self.descriptors: dict[int, np.ndarray] = {}
        """the latest descriptor of each landmark id the robot sent"""
        self.T: np.ndarray | None = None
        self.matches: list[CrossMatch] = []
        self.agreeing: list[CrossMatch] = []
        """the matches its transform is the mean of"""
        self.searched = 0
        """its keyframes looked for in the map so far"""
        self.joined = False
        """it tracks in the stored map (its frame is the map's, its landmark ids the stored map's rows)"""
        self.bytes_in = 0

    def __len__(self) -> int:
        return len(self.observations)

    @property
    def poses(self) -> np.ndarray:
        """(K, 4, 4) the current camera-to-world pose of each of its keyframes, in its own frame."""
        return self.all_poses[self.offset:self.offset + len(self)]

    @property
    def stamps(self) -> np.ndarray:
        return self.all_stamps[self.offset:self.offset + len(self)]

    def add(self, batch: KeyframeBatch) -> int:
        """Take a batch; returns how many keyframes were new."""
        for landmark_id, descriptor in zip(batch.described.tolist(), batch.descriptors, strict=True):
            self.descriptors[landmark_id] = descriptor
        self.all_poses, self.all_stamps = batch.poses.astype(np.float64), batch.stamps.astype(np.float64)
        if not self.observations:
            self.offset = batch.first
        new = 0
        for k in range(len(batch.keypoint_first) - 1):
            index = batch.first + k
            if index < self.offset + len(self.observations):
                continue  # sent again (a repeated message)
            part = slice(batch.keypoint_first[k], batch.keypoint_first[k + 1])
            ids = batch.landmark[part].astype(np.int64)
            known = np.array([i in self.descriptors for i in ids.tolist()], bool)
            ids = ids[known]
            world = batch.positions[part][known].astype(np.float64)
            descriptors = np.stack([self.descriptors[i] for i in ids.tolist()]) if len(ids) else np.zeros(
                (0, batch.descriptors.shape[1] if batch.descriptors.ndim == 2 else 0), np.float32)
            self.observations.append(Observations(
                batch.xy[part][known].astype(np.float64), batch.depth[part][known].astype(np.float64), ids,
                transform_points(invert_pose(self.all_poses[index]), world), descriptors))
            new += 1
        return new

    def landmarks_near(self, keyframe: int, neighbours: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids, positions in the robot's frame, descriptors) of the landmarks that a keyframe and its
        ``neighbours`` on either side observe, each once (the latest keyframe's view of it)."""
        chosen: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for k in range(max(0, keyframe - neighbours), min(len(self), keyframe + neighbours + 1)):
            seen = self.observations[k]
            world = transform_points(self.poses[k], seen.points)
            for i, landmark_id in enumerate(seen.landmark.tolist()):
                chosen[landmark_id] = (world[i], seen.descriptors[i])
        if not chosen:
            return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 0), np.float32)
        ids = np.fromiter(chosen, np.int64)
        return ids, np.stack([p for p, _ in chosen.values()]), np.stack([d for _, d in chosen.values()])


def pose_gap(T_1: np.ndarray, T_2: np.ndarray) -> tuple[float, float]:
    """(metres, degrees) between two poses."""
    delta = invert_pose(T_1) @ T_2
    return float(np.linalg.norm(delta[:3, 3])), float(np.degrees(rotation_angle(delta[:3, :3])))


def consistent_merge(matches: list[CrossMatch], k: int = 3, agree_m: float = 0.1,
                     agree_deg: float = 5.0) -> tuple[int, list[CrossMatch]] | None:
    """The first point in ``matches`` at which ``k`` of the matches so far give transforms within ``agree_m`` and
    ``agree_deg`` of one of them: (the index of the match that completed them, the agreeing matches); None if
    never."""
    for end in range(len(matches)):
        seen = matches[:end + 1]
        for centre in seen:
            close = [m for m in seen if all(gap <= limit for gap, limit in zip(
                pose_gap(centre.T_map_robot, m.T_map_robot), (agree_m, agree_deg), strict=True))]
            if len(close) >= k:
                return end, close
    return None


def mean_transform(transforms: list[np.ndarray]) -> np.ndarray:
    """The mean of rigid transforms: translations averaged, rotations by their chordal mean."""
    stacked = np.stack(transforms)
    T = np.eye(4)
    T[:3, :3] = nearest_rotation(stacked[:, :3, :3].sum(axis=0))
    T[:3, 3] = stacked[:, :3, 3].mean(axis=0)
    return T


class SharedMap:
    """One shared map while robots build it: a :class:`Submap` per robot, merged by recognised places (see the
    module docstring). ``match``: the descriptor matcher the verification uses; ``stored``: the map as stored,
    where it was (its frame is the map's, and robots that join track in it)."""

    def __init__(self, name: str, match: MatchFn, loop_closing: LoopClosingConfig | None = None,
                 tracking: TrackerConfig | None = None, stored: MapFile | None = None, k: int = 3,
                 agree_m: float = 0.1, agree_deg: float = 5.0) -> None:
        self.name, self.match, self.k, self.agree_m, self.agree_deg = name, match, k, agree_m, agree_deg
        self.conf = loop_closing or LoopClosingConfig()
        self.tracking = tracking or TrackerConfig()
        self.submaps: dict[str, Submap] = {}
        self.stored = stored
        if stored is not None:  # its keyframes are places of the map, as a robot's would be
            base = self.submaps[STORED] = Submap(STORED, "", stored.header.camera)
            base.T = np.eye(4)
            first, arrays = KeyframeSender().next(stored.arrays)
            base.add(KeyframeBatch(first=first, **arrays))
        self.vocabulary: Vocabulary | None = None
        self.index: PlaceIndex | None = None
        self.indexed: list[tuple[str, int]] = []  # the index's places: (robot, keyframe), by place number
        self.in_index: set[tuple[str, int]] = set()  # the places of ``indexed``, for a quick look-up
        self.built_from = 0  # keyframes in the map when the vocabulary was built

    def join(self, robot: str, session: str) -> MergeEvent | None:
        """A robot's session starts sharing the map. Where the map was stored, the robot tracks in it (its frame is
        the map's: ``joined``); otherwise the first robot's frame becomes the map's (``defines``), and any other
        starts in a submap of its own. Returns the event that places it in the map's frame, if it is placed now.
        A robot that comes back in a new session before the map was saved starts a new submap."""
        submap = self.submaps.get(robot)
        if submap is not None and submap.session == session:
            return None
        if submap is not None:  # its earlier keyframes stay in the map, as a robot of its own
            self.submaps[f"{robot}@{submap.session}"] = submap
        submap = self.submaps[robot] = Submap(robot, session)
        first = not any(s.T is not None for r, s in self.submaps.items() if r != robot)
        if self.stored is not None or first:
            submap.T = np.eye(4)
            submap.joined = self.stored is not None
            return MergeEvent(robot, session, "joined" if self.stored is not None else "defines", submap.T)
        return None

    def merged(self) -> dict[str, Submap]:
        """The submaps in the map's frame, by their key (a robot id, or :data:`STORED`)."""
        return {key: s for key, s in self.submaps.items() if s.T is not None}

    def add(self, robot: str, batch: KeyframeBatch, camera: CameraIntrinsics) -> MergeEvent | None:
        """A robot's keyframes, taken with ``camera``; where they merge it into the map (or, once merged, move its
        transform), the event."""
        submap = self.submaps[robot]
        submap.camera = camera
        submap.add(batch)
        if submap.T is not None and (submap.matches == [] or len(submap.agreeing) >= REFINE_MATCHES):
            return None  # it defined the map, or its transform rests on enough matches
        t0 = time.perf_counter()
        found = self._search(robot, submap)
        if not found:
            return None
        submap.matches += found
        if submap.T is not None:
            return self._refine(robot, submap, found[-1], t0)
        agreed = consistent_merge(submap.matches, self.k, self.agree_m, self.agree_deg)
        if agreed is None:
            return None
        end, close = agreed
        submap.agreeing = close
        submap.T = mean_transform([self.transform(m, submap) for m in close])
        self.index = None  # the map grew by a robot: its vocabulary is built again
        return MergeEvent(robot, submap.session, "merged", submap.T, close, len(submap), submap.matches[end].stamp,
                          (time.perf_counter() - t0) * 1000)

    def transform(self, match: CrossMatch, submap: Submap) -> np.ndarray:
        """A match's transform of the robot's frame into the map's, from both keyframes' current poses (bundle
        adjustment and loop closing move them after the match)."""
        other = self.submaps[match.into]
        return other.T @ other.poses[match.candidate] @ match.relative @ invert_pose(submap.poses[match.keyframe])

    def _refine(self, robot: str, submap: Submap, latest: CrossMatch, t0: float) -> MergeEvent | None:
        """A merged robot's transform again, as the mean of every match that agrees with it (each from the
        keyframes' current poses): the event where it moved by more than :data:`REFINE_MOVE_M` or
        :data:`REFINE_MOVE_DEG`, until :data:`REFINE_MATCHES` matches agree."""
        current = {id(m): self.transform(m, submap) for m in submap.matches}
        agreeing = [m for m in submap.matches if all(gap <= limit for gap, limit in zip(
            pose_gap(submap.T, current[id(m)]), (self.agree_m, self.agree_deg), strict=True))]
        if not agreeing:
            return None
        submap.agreeing = agreeing
        T = mean_transform([current[id(m)] for m in agreeing])
        metres, degrees = pose_gap(submap.T, T)
        if metres < REFINE_MOVE_M and degrees < REFINE_MOVE_DEG:
            return None
        submap.T = T
        return MergeEvent(robot, submap.session, "refined", T, agreeing, len(submap), latest.stamp,
                          (time.perf_counter() - t0) * 1000)

    def _search(self, key: str, submap: Submap) -> list[CrossMatch]:
        """The submap's keyframes not yet searched, each looked for among the other merged robots' keyframes."""
        if not self._index_ready():
            return []
        found = []
        while submap.searched < len(submap):
            keyframe = submap.searched
            submap.searched += 1
            if submap.T is not None and keyframe % REFINE_EVERY:
                continue
            match = self._find(key, submap, keyframe)
            if match is not None:
                found.append(match)
        return found

    def _index_ready(self) -> bool:
        """The place index over the merged robots' keyframes, built again (a new online vocabulary) when the map
        grew by :data:`REBUILD_GROWTH`; False while the map is too small to search."""
        mapped = sum(len(s) for s in self.merged().values())
        if mapped < MIN_MAP_KEYFRAMES:
            return False
        if self.index is None or mapped >= REBUILD_GROWTH * self.built_from:
            sets = [seen.descriptors for submap in self.merged().values() for seen in submap.observations
                    if len(seen.descriptors)]
            if sum(len(d) for d in sets) > VOCABULARY_SAMPLE:  # an even sample of each keyframe's descriptors
                step = int(np.ceil(sum(len(d) for d in sets) / VOCABULARY_SAMPLE))
                sets = [d[::step] for d in sets]
            try:
                self.vocabulary = Vocabulary.train(sets, ONLINE_WORDS, iterations=10,
                                                   card={"name": f"online ({self.name})", "trained_on": "the map"})
            except VocabularyError:
                return False  # too few descriptors yet
            self.index, self.indexed, self.in_index, self.built_from = PlaceIndex(ONLINE_WORDS), [], set(), mapped
        for key, submap in self.merged().items():  # places added since
            for k in range(len(submap)):
                if (key, k) not in self.in_index:
                    self._index_place(key, submap, k)
        return True

    def _index_place(self, key: str, submap: Submap, keyframe: int) -> None:
        descriptors = submap.observations[keyframe].descriptors
        if len(descriptors):
            self.index.add(len(self.indexed), self.vocabulary.vector(descriptors))
        self.indexed.append((key, keyframe))
        self.in_index.add((key, keyframe))

    def _find(self, mine: str, submap: Submap, keyframe: int, candidates: int = CANDIDATES) -> CrossMatch | None:
        """One keyframe looked for among the other robots' in the map: the best ``candidates`` by bag of words,
        each verified; the first that passes gives the match."""
        seen = submap.observations[keyframe]
        if len(seen.landmark) < self.conf.min_inliers:
            return None
        query_vector = self.vocabulary.vector(seen.descriptors)
        others = [place for place, (key, _) in enumerate(self.indexed) if key != mine]
        for place, score in self.index.search(query_vector, candidates, set(others).__contains__):
            key, candidate = self.indexed[place]
            other = self.submaps[key]
            ids, positions, descriptors = other.landmarks_near(candidate, self.conf.candidate_neighbours)
            if len(ids) < self.conf.min_inliers:
                continue
            query = PlaceQuery(keyframe, float(submap.stamps[keyframe]), seen.xy, seen.depth, seen.landmark,
                              seen.descriptors, [PlaceCandidate(candidate, score, ids, positions, descriptors,
                                                               other.poses[candidate])])
            verdict = verify(query, submap.camera.matrix, self.conf, self.tracking, self.match)
            if verdict.match is None:
                continue
            T_other_keyframe = other.poses[candidate] @ verdict.match.relative
            T_map_robot = other.T @ T_other_keyframe @ invert_pose(submap.poses[keyframe])
            return CrossMatch(keyframe, float(submap.stamps[keyframe]), key, candidate,
                              len(verdict.match.pairs), T_map_robot, verdict.match.pairs, verdict.match.relative)
        return None


@dataclass
class Exported:
    """A shared map's keyframes as one map's arrays: ``cameras[i]`` took the keyframes whose ``keyframe_camera`` is
    ``i``, on robot ``robots[i]`` ('' where not recorded: a stored map's own)."""

    arrays: MapArrays
    cameras: list[CameraIntrinsics]
    robots: list[str]


def export(shared_map: SharedMap, keys: list[str]) -> Exported:
    """The keyframes of the submaps ``keys`` (the merged ones, with the stored map's first, in the map's frame; or
    one robot's alone, in its own) as one map's arrays. Each robot's landmarks are its own rows, except those a
    merge matched to another robot's landmark (the inliers of its agreeing matches): those are fused into that
    one's row."""
    parts: dict[str, list] = {name: [] for name in ("poses", "stamps", "camera", "xy", "depth", "landmark")}
    positions, descriptors, counts = [], [], []
    rows: dict[tuple[str, int], int] = {}
    cameras: list[CameraIntrinsics] = []
    robots: list[str] = []
    stored = shared_map.stored if STORED in keys else None
    if stored is not None:  # as stored: its landmarks keep their rows
        arrays = stored.arrays
        parts["poses"].append(arrays.keyframe_poses)
        parts["stamps"].append(arrays.keyframe_stamps)
        parts["camera"].append(arrays.keyframe_camera)
        first = arrays.keyframe_first
        for k in range(len(arrays.keyframe_stamps)):
            part = slice(first[k], first[k + 1])
            parts["xy"].append(arrays.keypoint_xy[part])
            parts["depth"].append(arrays.keypoint_depth[part])
            parts["landmark"].append(arrays.keypoint_landmark[part])
        positions += list(arrays.landmark_positions)
        descriptors += list(arrays.landmark_descriptors)
        counts += list(arrays.landmark_accepted)
        rows.update({(STORED, i): i for i in range(len(arrays.landmark_positions))})
        cameras += [stored.header.camera, *stored.header.cameras]
        robots += stored.header.camera_robots or [""] * len(cameras)
    for key in keys:
        submap = shared_map.submaps[key]
        if key == STORED or not len(submap):
            continue
        T = submap.T if submap.T is not None else np.eye(4)
        fused = {(key, int(mine)): (m.into, int(theirs)) for m in submap.matches for mine, theirs in m.pairs}
        # a robot that tracks in the stored map observes its landmarks by their rows (unless its tracker filled a
        # retired row with a new landmark: kept apart where the two lie more than FUSE_M apart)
        stored_rows = len(stored.arrays.landmark_positions) if stored is not None and submap.joined else 0
        cameras.append(submap.camera)
        robots.append(submap.robot)
        camera = len(cameras) - 1
        for k, seen in enumerate(submap.observations):
            pose = T @ submap.poses[k]
            world = transform_points(pose, seen.points)
            ids = np.empty(len(seen.landmark), np.int64)
            for i, landmark_id in enumerate(seen.landmark.tolist()):
                row = rows.get((key, landmark_id), rows.get(fused.get((key, landmark_id), ("", -1))))
                if row is None and landmark_id < stored_rows and np.linalg.norm(
                        positions[landmark_id] - world[i]) <= FUSE_M:
                    row = rows[(key, landmark_id)] = landmark_id
                if row is None:
                    row = rows[(key, landmark_id)] = len(positions)
                    positions.append(world[i])
                    descriptors.append(seen.descriptors[i])
                    counts.append(0)
                counts[row] += 1
                ids[i] = row
            parts["poses"].append(pose[None])
            parts["stamps"].append(submap.stamps[k:k + 1])
            parts["camera"].append(np.array([camera]))
            parts["xy"].append(seen.xy)
            parts["depth"].append(seen.depth)
            parts["landmark"].append(ids)
    sizes = [len(x) for x in parts["landmark"]]
    dimension = len(descriptors[0]) if descriptors else 1
    dtype = descriptors[0].dtype if descriptors else np.float32
    landmarks = len(positions)
    arrays = MapArrays(
        keyframe_poses=np.concatenate(parts["poses"]) if parts["poses"] else np.zeros((0, 4, 4)),
        keyframe_stamps=np.concatenate(parts["stamps"]).astype(np.float64) if parts["stamps"] else np.zeros(0),
        keyframe_culled=np.zeros(sum(len(p) for p in parts["stamps"]), bool),
        keyframe_first=np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
        keypoint_xy=np.concatenate(parts["xy"]).astype(np.float32) if sizes else np.zeros((0, 2), np.float32),
        keypoint_depth=np.concatenate(parts["depth"]).astype(np.float32) if sizes else np.zeros(0, np.float32),
        keypoint_landmark=np.concatenate(parts["landmark"]).astype(np.int64) if sizes else np.zeros(0, np.int64),
        landmark_positions=np.array(positions, np.float64).reshape(landmarks, 3),
        landmark_descriptors=np.array(descriptors, dtype).reshape(landmarks, dimension),
        landmark_accepted=np.array(counts, np.int64), landmark_rejected=np.zeros(landmarks, np.int64),
        landmark_bad=np.zeros(landmarks, bool),
        keyframe_camera=np.concatenate(parts["camera"]).astype(np.int64) if parts["camera"] else np.zeros(0, np.int64))
    return Exported(arrays, cameras, robots)
