"""The typed configuration of twohr's ROS 2 side (output of poses, input of live cameras)."""

from __future__ import annotations

import re

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from twohr.messages import ID_PATTERN

from .rmw import qualified_name

_FRAME = re.compile(r"^[A-Za-z0-9_./{}-]{1,128}$")


class Ros2CameraInput(BaseModel):
    """A live RGB-D camera published by ROS 2 nodes: colour (``Image``, or ``CompressedImage`` on
    ``<color_topic>/compressed``), depth aligned to colour (``Image``, 16UC1 mm or 32FC1 m) and ``CameraInfo``."""

    model_config = ConfigDict(extra="forbid")

    robot_id: str = Field(pattern=ID_PATTERN, description="twohr robot whose camera key the frames go to")
    namespace: str = Field("/", description="ROS namespace of the camera topics")
    color_topic: str = "camera/color/image_raw"
    depth_topic: str = "camera/aligned_depth_to_color/image_raw"
    info_topic: str = "camera/color/camera_info"
    max_dt: float = Field(0.02, gt=0, description="colour and depth stamps closer than this (s) form one frame")

    def topics(self) -> dict[str, str]:
        """The fully qualified topics: ``color``, ``color_compressed``, ``depth``, ``info``."""
        color = qualified_name(self.namespace, self.color_topic)
        return {"color": color, "color_compressed": color + "/compressed",
                "depth": qualified_name(self.namespace, self.depth_topic),
                "info": qualified_name(self.namespace, self.info_topic)}


class Ros2Config(BaseModel):
    """ROS 2 interop over rmw_zenoh. ``{robot}`` in the namespace and frame ids is replaced by the robot id."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(False, description="publish poses as ROS 2 topics (twohr up starts the ros2 service)")
    domain_id: int = Field(0, ge=0, le=232, description="ROS_DOMAIN_ID")
    namespace: str = Field("/{robot}", description="ROS namespace of each robot's topics and node")
    node_name: str = Field("twohr", pattern=r"^[A-Za-z_][A-Za-z0-9_]*$")
    map_frame: str = Field("map", description="REP 105 map frame: twohr's world (the first camera's optical frame) "
                           "as the tracker's corrections (bundle adjustment) place it; PoseStamped and the corrected "
                           "paths are in it, and tf has map -> odom")
    odom_frame: str = Field("odom", description="REP 105 odom frame: the world of the online per-frame poses, which "
                            "drift; Odometry, the Path and tf odom -> camera are in it. map -> odom is the latest "
                            "correction (identity until the first one, reset at each new session)")
    camera_frame: str = Field("camera", description="child frame: the camera's optical frame (x right, y down)")
    pose_topic: str = "pose"
    odom_topic: str = "odom"
    tf_topic: str = "tf"
    path_topic: str = "path"
    corrected_topic: str = Field("path_corrected", description="nav_msgs/Path of the tracker's corrections: the "
                                 "keyframes after bundle adjustment while the session runs, then the refined "
                                 "trajectory of every frame when it ends")
    path_every: int = Field(10, ge=1, description="publish the Path at keyframes and at least every N poses")
    path_max_poses: int = Field(10_000, ge=1, description="oldest Path poses are dropped beyond this")
    correction_window: int = Field(300, ge=1, description="online poses kept per robot to find the keyframe a "
                                   "correction is anchored on (by stamp); a correction none of whose keyframes is "
                                   "among them leaves map -> odom as it was")
    diagnostics_topic: str = Field("/diagnostics", description="absolute topic of the diagnostic_msgs/DiagnosticArray "
                                   "made from each session status (the tracker's ok/degraded and why, the services' "
                                   "lifecycle)")
    camera_input: Ros2CameraInput | None = Field(None, description="a live ROS 2 camera to relay into twohr")

    @field_validator("map_frame", "odom_frame", "camera_frame")
    @classmethod
    def _frame(cls, value: str) -> str:
        if not _FRAME.match(value):
            raise ValueError(f"invalid frame id {value!r}")
        return value

    @field_validator("namespace", "pose_topic", "odom_topic", "tf_topic", "path_topic", "corrected_topic")
    @classmethod
    def _name(cls, value: str) -> str:
        qualified_name(value.replace("{robot}", "robot"), "x")
        return value

    @field_validator("diagnostics_topic")
    @classmethod
    def _absolute(cls, value: str) -> str:
        if not value.startswith("/"):
            raise ValueError(f"{value!r} is not absolute: /diagnostics is one topic for every robot")
        return qualified_name("/", value)

    @model_validator(mode="after")
    def _distinct_frames(self) -> Ros2Config:
        if len({self.map_frame, self.odom_frame, self.camera_frame}) < 3:
            raise ValueError(f"map_frame, odom_frame and camera_frame must differ, got {self.map_frame!r}, "
                             f"{self.odom_frame!r} and {self.camera_frame!r}")
        return self

    def robot_namespace(self, robot_id: str) -> str:
        """The robot's namespace, e.g. ``/robot1`` (``/`` for none)."""
        return "/" + self.namespace.replace("{robot}", robot_id).strip("/")

    def topic(self, robot_id: str, name: str) -> str:
        """A fully qualified topic of one robot, e.g. ``/robot1/pose``."""
        return qualified_name(self.robot_namespace(robot_id), name)

    def frame(self, robot_id: str, frame: str) -> str:
        return frame.replace("{robot}", robot_id)
