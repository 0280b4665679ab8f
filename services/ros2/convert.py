"""twohr messages to and from ROS 2 messages: poses out (PoseStamped, Odometry, TF, Path), session statuses out
(DiagnosticArray), camera frames in.

Pure functions and small stateful builders; no bus inside: the service publishes what they return.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np

from twohr.dataset import CameraIntrinsics
from twohr.geometry import invert_pose, make_pose, quat_to_rot, rot_to_quat
from twohr.keys import LIVE_SESSION
from twohr.messages import FrameMsg, MergeMsg, MessageError, PathMsg, PoseMsg, StatusMsg
from twohr.trajectory import Trajectory

from . import msgs
from .config import Ros2CameraInput, Ros2Config

#: depth units per metre of the frames made from ROS images (16UC1 is millimetres by REP 118)
ROS_DEPTH_FACTOR = 1000.0
#: a corrected keyframe and an online pose are the same frame when their stamps are this close (s)
MATCH_STAMP_TOLERANCE = 1e-3
#: diagnostic level of each state a twohr service reports on ``twohr/<robot>/status``; any other state is OK
DIAGNOSTIC_LEVELS: dict[str, int] = {
    "ok": msgs.DiagnosticStatus.OK, "running": msgs.DiagnosticStatus.OK, "started": msgs.DiagnosticStatus.OK,
    "live": msgs.DiagnosticStatus.OK, "relaying": msgs.DiagnosticStatus.OK,
    "degraded": msgs.DiagnosticStatus.WARN, "capped": msgs.DiagnosticStatus.WARN,
    "error": msgs.DiagnosticStatus.ERROR, "failed": msgs.DiagnosticStatus.ERROR,
    "stopped": msgs.DiagnosticStatus.STALE, "finished": msgs.DiagnosticStatus.STALE,
}


def _header(stamp: float, frame_id: str) -> msgs.Header:
    return msgs.Header(stamp=msgs.stamp(stamp), frame_id=frame_id)


def _ros_pose(x, y, z, qx, qy, qz, qw) -> msgs.Pose:
    return msgs.Pose(position=msgs.Point(x=x, y=y, z=z), orientation=msgs.Quaternion(x=qx, y=qy, z=qz, w=qw))


def _pose(pose: PoseMsg) -> msgs.Pose:
    return _ros_pose(*pose.position, *pose.orientation)


def _still() -> msgs.TwistWithCovariance:
    zero = msgs.Vector3(x=0.0, y=0.0, z=0.0)
    return msgs.TwistWithCovariance(twist=msgs.Twist(linear=zero, angular=zero), covariance=np.zeros(36))


def _matrix(position, orientation) -> np.ndarray:
    return make_pose(quat_to_rot(np.asarray(orientation, np.float64)), position)


def _pose_of(matrix: np.ndarray) -> msgs.Pose:
    return _ros_pose(*matrix[:3, 3].tolist(), *rot_to_quat(matrix[:3, :3]).reshape(4).tolist())


def _transform(header: msgs.Header, child: str, pose: msgs.Pose) -> msgs.TransformStamped:
    p = pose.position
    return msgs.TransformStamped(header=header, child_frame_id=child, transform=msgs.Transform(
        translation=msgs.Vector3(x=p.x, y=p.y, z=p.z), rotation=pose.orientation))


@dataclass
class RobotState:
    """What :class:`PoseOutputs` keeps of one robot's session, all of it bounded: the Path so far
    (``path_max_poses``), the latest online poses by stamp (``correction_window``) and the correction."""

    session_id: str
    poses: deque = field(default_factory=deque)
    since_last: int = 0
    #: (stamp, position, orientation) of the latest online poses, the drifting estimate in the odom frame
    online: deque = field(default_factory=deque)
    #: T_map_odom of the latest correction; None until the first one (identity)
    map_odom: np.ndarray | None = None
    #: the stamp of the keyframe the correction was anchored on, and how many corrections were applied
    anchor_stamp: float | None = None
    corrections: int = 0


class PoseOutputs:
    """Turns each twohr pose of a robot into the ROS 2 messages to publish, by fully qualified topic.

    Frames follow REP 105. The online per-frame poses are the drifting estimate, in ``odom``: every pose gives an
    Odometry (odom -> camera) and a TFMessage with both map -> odom (the latest correction) and odom -> camera,
    so a tf listener gets them together, and a PoseStamped in ``map`` (correction · online pose, what a navigation
    stack wants). The tracker's live corrections (:meth:`corrections`) set map -> odom so that the latest corrected
    keyframe the robot's recent poses hold lands where bundle adjustment put it; until the first one, and again at
    each new session of the robot, map -> odom is the identity.

    A Path (in ``odom``) is added at every keyframe and, since the camera-rate schedule flags only the keyframes it
    waits for, also whenever ``path_every`` poses went by without one; each such pose is appended to it. A pose with
    non-finite values or a zero quaternion is skipped."""

    def __init__(self, config: Ros2Config) -> None:
        self.config = config
        self.robots: dict[str, RobotState] = {}

    def topics(self, robot_id: str) -> dict[type, str]:
        c = self.config
        return {msgs.PoseStamped: c.topic(robot_id, c.pose_topic), msgs.Odometry: c.topic(robot_id, c.odom_topic),
                msgs.TFMessage: c.topic(robot_id, c.tf_topic), msgs.Path: c.topic(robot_id, c.path_topic)}

    def frames(self, robot_id: str) -> tuple[str, str, str]:
        """The robot's (map, odom, camera) frame ids."""
        c = self.config
        return c.frame(robot_id, c.map_frame), c.frame(robot_id, c.odom_frame), c.frame(robot_id, c.camera_frame)

    def state(self, robot_id: str, session_id: str) -> RobotState:
        """The robot's state for this session: a new session of the robot starts afresh (path, correction)."""
        state = self.robots.get(robot_id)
        if state is None or state.session_id != session_id:
            state = self.robots[robot_id] = RobotState(session_id, deque(maxlen=self.config.path_max_poses),
                                                       online=deque(maxlen=self.config.correction_window))
        return state

    def merge(self, merge: MergeMsg) -> list[tuple[str, msgs.TFMessage]]:
        """A robot placed in a shared map: its submap's frame ``<map>/<robot>`` (where its odom hung before the
        merge) under the map's frame, by the merge's transform; its later poses come in the map's frame itself."""
        header = _header(merge.at, merge.map_name)
        child = f"{merge.map_name}/{merge.robot_id}"
        placed = _pose_of(merge.transform)
        tf = msgs.TFMessage(transforms=[_transform(header, child, placed)])
        return [(self.topics(merge.robot_id)[msgs.TFMessage], tf)]

    def messages(self, pose: PoseMsg) -> list[tuple[str, object]]:
        """``(topic, message)`` pairs for one pose, in publishing order."""
        if not np.all(np.isfinite(pose.position + pose.orientation)) or not any(pose.orientation):
            return []
        robot = pose.robot_id
        state = self.state(robot, pose.session_id)
        state.online.append((pose.stamp, tuple(pose.position), tuple(pose.orientation)))
        topics = self.topics(robot)
        map_frame, odom_frame, camera_frame = self.frames(robot)
        map_frame = pose.frame_id or map_frame  # a session in a named map: its poses are in that map's frame
        online = _pose(pose)
        odom_header = _header(pose.stamp, odom_frame)
        if state.map_odom is None:
            map_odom, in_map = _ros_pose(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0), online
        else:
            map_odom = _pose_of(state.map_odom)
            in_map = _pose_of(state.map_odom @ _matrix(pose.position, pose.orientation))
        stamped = msgs.PoseStamped(header=_header(pose.stamp, map_frame), pose=in_map)
        odometry = msgs.Odometry(header=odom_header, child_frame_id=camera_frame,
                                 pose=msgs.PoseWithCovariance(pose=online, covariance=np.zeros(36)), twist=_still())
        tf = msgs.TFMessage(transforms=[_transform(stamped.header, odom_frame, map_odom),
                                        _transform(odom_header, camera_frame, online)])
        out: list[tuple[str, object]] = [
            (topics[msgs.PoseStamped], stamped), (topics[msgs.Odometry], odometry), (topics[msgs.TFMessage], tf)]
        path = self._path(state, pose, msgs.PoseStamped(header=odom_header, pose=online))
        if path is not None:
            out.append((topics[msgs.Path], path))
        return out

    def corrections(self, path: PathMsg, trajectory: Trajectory) -> list[tuple[str, msgs.Path]]:
        """A corrected path from the tracker (keyframes after bundle adjustment, or the refined trajectory at the
        session's end) as one nav_msgs/Path on ``corrected_topic``, in the map frame. A live one (not ``final``)
        of the robot's current session also moves map -> odom: see :meth:`correct`."""
        robot = path.robot_id
        map_frame = path.frame_id or self.config.frame(robot, self.config.map_frame)  # a named map's own frame
        state = self.robots.get(robot)
        if not path.final and state is not None and state.session_id == path.session_id:
            self.correct(state, trajectory)
        rows = trajectory.to_tum_array() if len(trajectory) else np.zeros((0, 8))
        poses = [msgs.PoseStamped(header=_header(float(r[0]), map_frame), pose=_ros_pose(*r[1:].tolist()))
                 for r in rows if np.isfinite(r).all()]
        topic = self.config.topic(robot, self.config.corrected_topic)
        return [(topic, msgs.Path(header=_header(path.stamp, map_frame), poses=poses))]

    @staticmethod
    def correct(state: RobotState, keyframes: Trajectory) -> bool:
        """Set ``T_map_odom = T_corrected(kf) · T_online(kf)^-1`` for the latest keyframe of ``keyframes`` whose
        stamp is within :data:`MATCH_STAMP_TOLERANCE` of an online pose the robot still holds. False, and the
        previous correction kept, when none is."""
        if not len(keyframes) or not state.online:
            return False
        online_stamps = np.array([stamp for stamp, _, _ in state.online])
        order = np.argsort(online_stamps, kind="stable")
        ordered = online_stamps[order]
        at = np.searchsorted(ordered, keyframes.stamps)
        below, above = np.clip(at - 1, 0, len(ordered) - 1), np.clip(at, 0, len(ordered) - 1)
        nearest = np.where(np.abs(ordered[below] - keyframes.stamps) <= np.abs(ordered[above] - keyframes.stamps),
                           below, above)
        gap = np.abs(ordered[nearest] - keyframes.stamps)
        finite = np.isfinite(keyframes.poses).all(axis=(1, 2))
        matched = np.flatnonzero((gap <= MATCH_STAMP_TOLERANCE) & finite)
        if not len(matched):
            return False
        latest = matched[np.argmax(keyframes.stamps[matched])]
        stamp, position, orientation = state.online[int(order[nearest[latest]])]
        correction = keyframes.poses[latest] @ invert_pose(_matrix(position, orientation))
        state.map_odom, state.anchor_stamp = correction, float(stamp)
        state.corrections += 1
        return True

    def _path(self, state: RobotState, pose: PoseMsg, stamped: msgs.PoseStamped) -> msgs.Path | None:
        state.since_last += 1
        if not pose.is_keyframe and state.since_last < self.config.path_every:
            return None
        state.since_last = 0
        state.poses.append(stamped)
        return msgs.Path(header=stamped.header, poses=list(state.poses))


def diagnostics(status: StatusMsg, config: Ros2Config) -> tuple[str, msgs.DiagnosticArray]:
    """A session status (the tracker's ``ok``/``degraded`` and why with its figures, or a service's lifecycle) as a
    ``diagnostic_msgs/DiagnosticArray`` for ``diagnostics_topic``: one DiagnosticStatus named
    ``twohr/<robot>/<service>``, its level from :data:`DIAGNOSTIC_LEVELS`, the detail as its message, the robot as
    its hardware id, and the state, the session and the figures as key/value pairs."""
    values = [msgs.KeyValue(key="state", value=status.state), msgs.KeyValue(key="session_id", value=status.session_id)]
    values += [msgs.KeyValue(key=key, value=str(value)) for key, value in status.counters.items()]
    entry = msgs.DiagnosticStatus(level=DIAGNOSTIC_LEVELS.get(status.state, msgs.DiagnosticStatus.OK),
                                  name=f"twohr/{status.robot_id}/{status.service or 'tracker'}",
                                  message=status.detail or status.state, hardware_id=status.robot_id, values=values)
    return config.diagnostics_topic, msgs.DiagnosticArray(header=_header(status.stamp, ""), status=[entry])


# -- camera frames ---------------------------------------------------------------------------------------------

_COLOR = {"rgb8": (3, None), "bgr8": (3, cv2.COLOR_BGR2RGB), "rgba8": (4, cv2.COLOR_RGBA2RGB),
          "bgra8": (4, cv2.COLOR_BGRA2RGB), "mono8": (1, cv2.COLOR_GRAY2RGB)}


def _rows(image: msgs.Image, channels: int, dtype: np.dtype) -> np.ndarray:
    dtype = np.dtype(dtype).newbyteorder(">" if image.is_bigendian else "<")
    row = image.width * channels * dtype.itemsize
    if image.step < row or len(image.data) < image.step * image.height:
        raise MessageError(f"{image.encoding} image {image.width}x{image.height}: step {image.step}, "
                           f"{len(image.data)} bytes do not hold it")
    rows = np.frombuffer(image.data, np.uint8, count=image.step * image.height).reshape(image.height, image.step)
    pixels = rows[:, :row].copy().view(dtype).reshape(image.height, image.width, channels)
    return pixels.astype(dtype.newbyteorder("="))


def color_image(image: msgs.Image | msgs.CompressedImage) -> np.ndarray:
    """An (H, W, 3) uint8 RGB array from a colour ``Image`` (rgb8, bgr8, rgba8, bgra8, mono8) or a
    JPEG/PNG ``CompressedImage``; raises :class:`MessageError` on anything else."""
    if isinstance(image, msgs.CompressedImage):
        decoded = cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_COLOR)
        if decoded is None:
            raise MessageError(f"corrupt compressed colour image (format {image.format!r})")
        return cv2.cvtColor(decoded, cv2.COLOR_BGR2RGB)
    if image.encoding not in _COLOR:
        raise MessageError(f"unsupported colour encoding {image.encoding!r}: use one of {sorted(_COLOR)}")
    channels, conversion = _COLOR[image.encoding]
    pixels = _rows(image, channels, np.uint8)
    pixels = pixels[:, :, 0] if channels == 1 else pixels
    return np.ascontiguousarray(pixels if conversion is None else cv2.cvtColor(pixels, conversion))


def depth_image(image: msgs.Image) -> np.ndarray:
    """An (H, W) uint16 depth array in millimetres (0 = no reading) from a 16UC1 (mm) or 32FC1 (m) ``Image``."""
    if image.encoding in ("16UC1", "mono16"):
        return _rows(image, 1, np.uint16)[:, :, 0]
    if image.encoding == "32FC1":
        metres = _rows(image, 1, np.float32)[:, :, 0]
        metres = np.where(np.isfinite(metres) & (metres > 0), metres, 0.0)
        return np.clip(np.round(metres * ROS_DEPTH_FACTOR), 0, 65535).astype(np.uint16)
    raise MessageError(f"unsupported depth encoding {image.encoding!r}: use 16UC1 (mm) or 32FC1 (m)")


def intrinsics(info: msgs.CameraInfo) -> CameraIntrinsics:
    """Pinhole intrinsics (and plumb-bob distortion, if any) of a ``CameraInfo``, depth in millimetres."""
    fx, _, cx, _, fy, cy = info.k[:6]
    if fx <= 0 or fy <= 0 or info.width <= 0 or info.height <= 0:
        raise MessageError(f"CameraInfo without a calibration (K = {info.k}, {info.width}x{info.height})")
    distortion = [float(v) for v in info.d[:5]] if any(info.d) else []
    if distortion and info.distortion_model not in ("plumb_bob", "rational_polynomial"):
        raise MessageError(f"unsupported distortion model {info.distortion_model!r}")
    distortion += [0.0] * (5 - len(distortion)) if distortion else []
    return CameraIntrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=info.width, height=info.height,
                            depth_factor=ROS_DEPTH_FACTOR, distortion=distortion)


class CameraAssembler:
    """Pairs colour and depth images by stamp (within ``max_dt``) and adds the latest ``CameraInfo``:
    each complete pair becomes one twohr frame for ``twohr/<robot>/camera``. Unpaired images older
    than a paired one are dropped and counted."""

    def __init__(self, config: Ros2CameraInput, keep: int = 8) -> None:
        self.config = config
        self.info: msgs.CameraInfo | None = None
        self.colors: deque[tuple[float, msgs.Image | msgs.CompressedImage]] = deque(maxlen=keep)
        self.depths: deque[tuple[float, msgs.Image]] = deque(maxlen=keep)
        self.frames = 0
        self.unpaired = 0
        self.without_info = 0

    def add_info(self, info: msgs.CameraInfo) -> None:
        self.info = info

    def add_color(self, image: msgs.Image | msgs.CompressedImage) -> tuple[FrameMsg, dict] | None:
        self.colors.append((msgs.seconds(image.header.stamp), image))
        return self._pair()

    def add_depth(self, image: msgs.Image) -> tuple[FrameMsg, dict] | None:
        self.depths.append((msgs.seconds(image.header.stamp), image))
        return self._pair()

    def _pair(self) -> tuple[FrameMsg, dict] | None:
        best = None
        for i, (tc, _) in enumerate(self.colors):
            for j, (td, _) in enumerate(self.depths):
                if abs(tc - td) <= self.config.max_dt and (best is None or abs(tc - td) < best[0]):
                    best = (abs(tc - td), i, j)
        if best is None:
            return None
        _, i, j = best
        stamp, color = self.colors[i]
        _, depth = self.depths[j]
        self.unpaired += i + j  # everything older than the pair will never be paired now
        for _ in range(i + 1):
            self.colors.popleft()
        for _ in range(j + 1):
            self.depths.popleft()
        if self.info is None:
            self.without_info += 1
            return None
        return self.frame(stamp, color, depth, self.info)

    def frame(self, stamp: float, color: msgs.Image | msgs.CompressedImage, depth: msgs.Image,
              info: msgs.CameraInfo) -> tuple[FrameMsg, dict]:
        """One twohr frame (message and arrays) from a colour image, its aligned depth and the camera info."""
        rgb, depth_mm, camera = color_image(color), depth_image(depth), intrinsics(info)
        if rgb.shape[:2] != depth_mm.shape or rgb.shape[:2] != (camera.height, camera.width):
            raise MessageError(f"colour {rgb.shape[1]}x{rgb.shape[0]}, depth {depth_mm.shape[1]}x{depth_mm.shape[0]} "
                               f"and CameraInfo {camera.width}x{camera.height} differ: depth must be aligned to colour")
        message = FrameMsg(session_id=LIVE_SESSION, robot_id=self.config.robot_id, frame_index=self.frames,
                           stamp=stamp, camera=camera)
        self.frames += 1
        return message, {"rgb": rgb, "depth": depth_mm}


def frame_to_ros(stamp: float, rgb: np.ndarray, depth: np.ndarray, camera: CameraIntrinsics, frame_id: str = "camera"
                 ) -> tuple[msgs.Image, msgs.Image, msgs.CameraInfo]:
    """A twohr frame as a ROS 2 camera would publish it: rgb8 colour, 16UC1 depth in mm, CameraInfo."""
    header = _header(stamp, frame_id)
    height, width = depth.shape
    millimetres = np.clip(np.round(depth.astype(np.float64) * ROS_DEPTH_FACTOR / camera.depth_factor), 0, 65535)
    color = msgs.Image(header=header, height=height, width=width, encoding="rgb8", is_bigendian=0, step=width * 3,
                       data=np.ascontiguousarray(rgb, np.uint8).reshape(-1))
    depth_msg = msgs.Image(header=header, height=height, width=width, encoding="16UC1", is_bigendian=0,
                           step=width * 2, data=millimetres.astype("<u2").view(np.uint8).reshape(-1))
    k = [camera.fx, 0.0, camera.cx, 0.0, camera.fy, camera.cy, 0.0, 0.0, 1.0]
    p = [camera.fx, 0.0, camera.cx, 0.0, 0.0, camera.fy, camera.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    info = msgs.CameraInfo(header=header, height=height, width=width, distortion_model="plumb_bob",
                           d=np.array(list(camera.distortion) or [0.0] * 5), k=np.array(k), r=np.eye(3).reshape(-1),
                           p=np.array(p), binning_x=0, binning_y=0,
                           roi=msgs.RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
    return color, depth_msg, info
