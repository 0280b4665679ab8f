"""What a robot's tracker tells the map server of its map, in a session that shares one.

:class:`KeyframeSender` turns copies of the robot's map (:class:`~twohr.mapfile.MapArrays`) into
:class:`~twohr.messages.KeyframesMsg` arrays: every keyframe's current pose, the observations of the keyframes not
sent yet, and each landmark's descriptor once (again only where it changed: a retired landmark's row is filled by a
new one). The map server reads a stored map the same way."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from twohr.mapfile import MapArrays


@dataclass
class KeyframeSender:
    """The keyframes and descriptors the map server has of this robot's map."""

    keyframes: int = 0
    descriptors: dict[int, bytes] = field(default_factory=dict)
    """each descriptor as last sent, by landmark id (bounded as the map's landmark rows are)"""
    bytes_sent: int = 0

    def next(self, arrays: MapArrays, final: bool = False) -> tuple[int, dict[str, np.ndarray]] | None:
        """(``first``, the message's arrays) for the keyframes of ``arrays`` not sent yet; None where there are
        none (unless ``final``: the last poses go anyway)."""
        count = len(arrays.keyframe_stamps)
        if count <= self.keyframes and not final:
            return None
        first = min(self.keyframes, count)
        descriptors = arrays.landmark_descriptors
        start, end = arrays.keyframe_first[first], arrays.keyframe_first[count]
        ids = arrays.keypoint_landmark[start:end]
        observed = np.flatnonzero(ids >= 0)  # of the new keyframes' keypoints: those on a described, good landmark
        seen = ids[observed]
        rows = start + observed[~arrays.landmark_bad[seen] & np.any(descriptors[seen] != 0, axis=1)]
        splits = np.searchsorted(rows, arrays.keyframe_first[first:count + 1])
        landmark = arrays.keypoint_landmark[rows]
        changed = [i for i in np.unique(landmark).tolist() if self.descriptors.get(i) != descriptors[i].tobytes()]
        for i in changed:
            self.descriptors[i] = descriptors[i].tobytes()
        self.keyframes = count
        return first, {
            "poses": arrays.keyframe_poses.astype(np.float32), "stamps": arrays.keyframe_stamps.astype(np.float64),
            "keypoint_first": splits.astype(np.int64), "xy": arrays.keypoint_xy[rows].astype(np.float32),
            "depth": arrays.keypoint_depth[rows].astype(np.float32), "landmark": landmark.astype(np.int64),
            "positions": arrays.landmark_positions[landmark].astype(np.float32),
            "described": np.array(changed, np.int64),
            "descriptors": descriptors[np.array(changed, np.int64)] if changed else np.zeros(
                (0, descriptors.shape[1]), descriptors.dtype)}
