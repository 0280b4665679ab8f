"""twohr data -> Foxglove well-known messages (foxglove-sdk's typed schemas), for recordings and the live view.

One converter serves the recorder (MCAP) and the live views (Foxglove WebSocket on the gateway, and
``twohr run --view``), so all show the same channels. Per robot (see :func:`topics`): the colour image
(``CompressedImage``), its keypoints and the dynamic mask's outlines (two ``ImageAnnotations`` topics), the camera
(``CameraCalibration``), the pose (``PoseInFrame``), the path so far (``PosesInFrame``), the map points
(``PointCloud``), and ``world`` -> ``<robot>/camera`` on ``/tf`` (``FrameTransforms``).
"""

from __future__ import annotations

import collections
import math

import cv2
import numpy as np
from foxglove import messages as fm

from .dataset import CameraIntrinsics
from .messages import (
    DynamicsMsg,
    FrameMsg,
    KeypointsMsg,
    LandmarksMsg,
    MergeMsg,
    PathAssembler,
    PathMsg,
    PoseMsg,
    decode,
    split,
)
from .trajectory import Trajectory

WORLD = "world"
TF_TOPIC = "/tf"
KEYPOINT_COLOR = fm.Color(r=0.1, g=1.0, b=0.2, a=1.0)
MASK_COLOR = fm.Color(r=1.0, g=0.2, b=0.2, a=1.0)
NO_FILL = fm.Color(r=0.0, g=0.0, b=0.0, a=0.0)


def topics(robot_id: str) -> dict[str, str]:
    """The Foxglove topic of each kind of data, for one robot."""
    return {"image": f"/{robot_id}/camera/image", "keypoints": f"/{robot_id}/camera/keypoints",
            "dynamic_mask": f"/{robot_id}/camera/dynamic_mask",
            "calibration": f"/{robot_id}/camera/calibration", "pose": f"/{robot_id}/pose",
            "path": f"/{robot_id}/path", "keyframes": f"/{robot_id}/keyframes",
            "path_refined": f"/{robot_id}/path_refined", "map": f"/{robot_id}/map", "tf": TF_TOPIC}


#: the Foxglove message type of each kind of topic in :func:`topics`
TOPIC_TYPES: dict[str, type] = {
    "image": fm.CompressedImage, "keypoints": fm.ImageAnnotations, "dynamic_mask": fm.ImageAnnotations,
    "calibration": fm.CameraCalibration, "pose": fm.PoseInFrame, "path": fm.PosesInFrame,
    "keyframes": fm.PosesInFrame, "path_refined": fm.PosesInFrame, "map": fm.PointCloud, "tf": fm.FrameTransforms,
}


def camera_frame(robot_id: str) -> str:
    return f"{robot_id}/camera"


def drawn_in(frame_id: str) -> str:
    """The Foxglove frame of poses in ``frame_id``: a robot's submap of a shared map (``lab/b``, before its merge)
    is its own frame, hung under the world by the merge's transform (:meth:`FoxgloveConverter.merge`); any other is the
    world."""
    return frame_id if "/" in frame_id else WORLD


def timestamp(seconds: float) -> fm.Timestamp:
    sec = math.floor(seconds)
    return fm.Timestamp(sec, min(999_999_999, round((seconds - sec) * 1e9)))


def jpeg(rgb: np.ndarray, quality: int) -> bytes:
    """An RGB image as JPEG bytes."""
    ok, data = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("cannot encode the image as JPEG")
    return data.tobytes()


def compressed_image(stamp: float, frame_id: str, data: bytes, fmt: str = "jpeg") -> fm.CompressedImage:
    return fm.CompressedImage(timestamp=timestamp(stamp), frame_id=frame_id, data=data, format=fmt)


def calibration(stamp: float, frame_id: str, camera: CameraIntrinsics) -> fm.CameraCalibration:
    """A pinhole ``plumb_bob`` calibration; the depth is registered to this colour camera."""
    k = [camera.fx, 0.0, camera.cx, 0.0, camera.fy, camera.cy, 0.0, 0.0, 1.0]
    return fm.CameraCalibration(timestamp=timestamp(stamp), frame_id=frame_id, width=camera.width,
                                height=camera.height, distortion_model="plumb_bob",
                                D=list(camera.distortion) or [0.0] * 5, K=k,
                                R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                                P=[camera.fx, 0.0, camera.cx, 0.0, 0.0, camera.fy, camera.cy, 0.0, 0.0, 0.0, 1.0, 0.0])


def vector3(position) -> fm.Vector3:
    x, y, z = (float(v) for v in position)
    return fm.Vector3(x=x, y=y, z=z)


def quaternion(orientation) -> fm.Quaternion:
    """A quaternion given as (x, y, z, w)."""
    x, y, z, w = (float(v) for v in orientation)
    return fm.Quaternion(x=x, y=y, z=z, w=w)


def pose(position, orientation) -> fm.Pose:
    """A pose from a position (x, y, z) and a quaternion (x, y, z, w)."""
    return fm.Pose(position=vector3(position), orientation=quaternion(orientation))


def pose_in_frame(stamp: float, position, orientation, frame_id: str = WORLD) -> fm.PoseInFrame:
    return fm.PoseInFrame(timestamp=timestamp(stamp), frame_id=frame_id, pose=pose(position, orientation))


def poses_in_frame(stamp: float, positions, orientations, frame_id: str = WORLD) -> fm.PosesInFrame:
    return fm.PosesInFrame(timestamp=timestamp(stamp), frame_id=frame_id,
                           poses=[pose(p, q) for p, q in zip(positions, orientations, strict=True)])


def frame_transforms(stamp: float, parent: str, child: str, position, orientation) -> fm.FrameTransforms:
    return fm.FrameTransforms(transforms=[fm.FrameTransform(
        timestamp=timestamp(stamp), parent_frame_id=parent, child_frame_id=child, translation=vector3(position),
        rotation=quaternion(orientation))])


_XYZ_FIELDS = [fm.PackedElementField(name=name, offset=4 * i, type=fm.PackedElementFieldNumericType.Float32)
               for i, name in enumerate("xyz")]


def point_cloud(stamp: float, points: np.ndarray, frame_id: str = WORLD) -> fm.PointCloud:
    """(N, 3) world points as a packed float32 x, y, z cloud."""
    data = np.ascontiguousarray(np.asarray(points, np.float32).reshape(-1, 3)).tobytes()
    return fm.PointCloud(timestamp=timestamp(stamp), frame_id=frame_id, pose=pose((0, 0, 0), (0, 0, 0, 1)),
                         point_stride=12, fields=_XYZ_FIELDS, data=data)


def mask_outlines(mask: np.ndarray, max_points: int = 64) -> list[np.ndarray]:
    """The outer outlines of a boolean mask's regions, each simplified to at most about ``max_points`` corners."""
    contours, _ = cv2.findContours(np.asarray(mask, np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    outlines = []
    for contour in contours:
        if len(contour) < 3:
            continue
        epsilon = max(1.0, cv2.arcLength(contour, True) / max_points)
        outlines.append(cv2.approxPolyDP(contour, epsilon, True).reshape(-1, 2))
    return outlines


def image_annotations(stamp: float, keypoints: np.ndarray | None = None,
                      outlines: list[np.ndarray] | None = None) -> fm.ImageAnnotations:
    """Keypoints (N, 2 pixels) as green dots and dynamic regions (polygons) as red outlines."""
    t = timestamp(stamp)
    points = []
    if keypoints is not None and len(keypoints):
        # +0.5: Foxglove's pixel origin is the top-left corner of the top-left pixel, ours its centre
        points.append(fm.PointsAnnotation(timestamp=t, type=fm.PointsAnnotationType.Points, thickness=4.0,
                                          points=[fm.Point2(x=float(x) + 0.5, y=float(y) + 0.5)
                                                  for x, y in np.asarray(keypoints).reshape(-1, 2)],
                                          outline_color=KEYPOINT_COLOR, fill_color=KEYPOINT_COLOR))
    for outline in outlines or []:
        points.append(fm.PointsAnnotation(timestamp=t, type=fm.PointsAnnotationType.LineLoop, thickness=2.0,
                                          points=[fm.Point2(x=float(x) + 0.5, y=float(y) + 0.5) for x, y in outline],
                                          outline_color=MASK_COLOR, fill_color=NO_FILL))
    return fm.ImageAnnotations(timestamp=t, points=points)


class FoxgloveConverter:
    """twohr data of any number of robots -> ``(topic, Foxglove message)`` pairs. Keeps each robot's recent path.

    ``jpeg_quality`` re-encodes colour images (None passes JPEG bytes through as they arrived);
    ``path_every`` sends the path with every n-th pose: its latest ``path_window`` poses, so that neither the
    converter's memory nor the messages grow with a session that runs for hours. The corrected keyframes of the
    tracker's live corrections go on ``keyframes``, and the refined trajectory at a session's end on
    ``path_refined``."""

    def __init__(self, jpeg_quality: int | None = 80, path_every: int = 10, path_window: int = 1800) -> None:
        self.jpeg_quality = jpeg_quality
        self.path_every = max(1, path_every)
        self.path_window = max(1, path_window)
        self.paths: dict[str, tuple[collections.deque, collections.deque, list[int]]] = {}
        self.frames: dict[str, str] = {}  # the frame each robot's path is drawn in
        self.assembler = PathAssembler()

    def reset(self, robot_id: str) -> None:
        """Forget a robot's path (a new session starts)."""
        self.paths.pop(robot_id, None)
        self.frames.pop(robot_id, None)

    def frame(self, robot_id: str, stamp: float, camera: CameraIntrinsics, rgb: np.ndarray | None = None,
              encoded: bytes | None = None, encoding: str = "jpeg") -> list[tuple[str, object]]:
        """The colour image (an array, or its encoded bytes) and the camera calibration."""
        if encoded is None:
            encoded, encoding = jpeg(rgb, self.jpeg_quality or 90), "jpeg"
        elif self.jpeg_quality is not None:
            image = cv2.imdecode(np.frombuffer(encoded, np.uint8), cv2.IMREAD_COLOR)
            if image is None:
                raise ValueError("corrupt colour image")
            encoded, encoding = jpeg(cv2.cvtColor(image, cv2.COLOR_BGR2RGB), self.jpeg_quality), "jpeg"
        names = topics(robot_id)
        frame_id = camera_frame(robot_id)
        return [(names["image"], compressed_image(stamp, frame_id, encoded, encoding)),
                (names["calibration"], calibration(stamp, frame_id, camera))]

    def keypoints(self, robot_id: str, stamp: float, xy: np.ndarray) -> list[tuple[str, object]]:
        """Keypoints (N, 2 pixels) drawn on the image."""
        return [(topics(robot_id)["keypoints"], image_annotations(stamp, keypoints=xy))]

    def dynamic_mask(self, robot_id: str, stamp: float, mask: np.ndarray) -> list[tuple[str, object]]:
        """The outlines of the pixels masked as dynamic, drawn on the image."""
        outlines = mask_outlines(mask) if mask.any() else []
        return [(topics(robot_id)["dynamic_mask"], image_annotations(stamp, outlines=outlines))]

    def pose(self, robot_id: str, stamp: float, position, orientation, frame: str = WORLD
             ) -> list[tuple[str, object]]:
        """The pose, the transform on /tf and, every ``path_every`` poses, the path so far."""
        names = topics(robot_id)
        if self.frames.setdefault(robot_id, frame) != frame:  # merged into a shared map: the path starts again
            self.frames[robot_id] = frame
            self.paths.pop(robot_id, None)
        out = [(names["pose"], pose_in_frame(stamp, position, orientation, frame)),
               (names["tf"], frame_transforms(stamp, frame, camera_frame(robot_id), position, orientation))]
        positions, orientations, count = self.paths.setdefault(
            robot_id, (collections.deque(maxlen=self.path_window), collections.deque(maxlen=self.path_window), [0]))
        positions.append(list(position))
        orientations.append(list(orientation))
        count[0] += 1
        if (count[0] - 1) % self.path_every == 0:
            out.append((names["path"], poses_in_frame(stamp, list(positions), list(orientations), frame)))
        return out

    def corrected_path(self, robot_id: str, stamp: float, trajectory: Trajectory, final: bool, frame: str = WORLD
                       ) -> list[tuple[str, object]]:
        """A tracker's corrected path: the keyframes after bundle adjustment (live), or the refined trajectory of
        every frame (``final``, at the session's end)."""
        rows = trajectory.to_tum_array()
        topic = topics(robot_id)["path_refined" if final else "keyframes"]
        return [(topic, poses_in_frame(stamp, rows[:, 1:4].tolist(), rows[:, 4:8].tolist(), frame))]

    def merge(self, merge: MergeMsg) -> list[tuple[str, object]]:
        """A robot merged into a shared map: its submap's frame placed in the world (the map's frame), so that
        what it drew before the merge lands where it belongs."""
        return [(TF_TOPIC, frame_transforms(merge.at, WORLD, f"{merge.map_name}/{merge.robot_id}", merge.position,
                                            merge.orientation))]

    def landmarks(self, robot_id: str, stamp: float, points: np.ndarray) -> list[tuple[str, object]]:
        return [(topics(robot_id)["map"], point_cloud(stamp, points))]

    def convert(self, payload: bytes) -> list[tuple[str, object]]:
        """Foxglove messages for one bus message (none for streams they do not show). Raises ``MessageError``."""
        message, parts = split(payload)
        robot, t = message.robot_id, message.stamp
        if isinstance(message, FrameMsg):
            spec, blob = next((s, b) for s, b in parts if s.name == "rgb")
            if spec.encoding == "raw":
                _, arrays = decode(payload, only=("rgb",))
                return self.frame(robot, t, message.camera, rgb=arrays["rgb"])
            return self.frame(robot, t, message.camera, encoded=blob, encoding=spec.encoding)
        if isinstance(message, KeypointsMsg):
            _, arrays = decode(payload, only=("xy",))
            return self.keypoints(robot, t, arrays["xy"])
        if isinstance(message, DynamicsMsg):
            _, arrays = decode(payload, only=("mask",))
            return self.dynamic_mask(robot, t, arrays["mask"].astype(bool))
        if isinstance(message, PoseMsg):
            return self.pose(robot, t, message.position, message.orientation, drawn_in(message.frame_id))
        if isinstance(message, LandmarksMsg):
            _, arrays = decode(payload, only=("points",))
            return self.landmarks(robot, t, arrays["points"])
        if isinstance(message, PathMsg):
            _, arrays = decode(payload)
            trajectory = self.assembler.add(message, arrays)  # the whole path, rebuilt from deltas
            return [] if trajectory is None else self.corrected_path(robot, t, trajectory, message.final,
                                                                     drawn_in(message.frame_id))
        if isinstance(message, MergeMsg):
            return self.merge(message)
        return []
