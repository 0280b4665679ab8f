"""The constant-velocity motion model shared by the keyframe tracker and the per-frame flow tracker."""

from __future__ import annotations

import numpy as np

from twohr.config import TrackerConfig
from twohr.geometry import invert_pose, so3_exp_batch, so3_log
from twohr.pose import MotionPrior, pose_difference, scale_motion

#: Nominal frame interval used when stamps do not advance (seconds).
NOMINAL_FRAME_DT = 1 / 30


class MotionModel:
    """Predicts the next camera-to-world pose from the mean motion of the latest tracked frames.

    ``last_pose`` is the previous frame's pose (tracked or coasted), ``good_pose`` the latest tracked
    one, ``lost_frames`` how many frames in a row could not be tracked (gates widen with it).
    """

    def __init__(self, velocity_frames: int = 5, coast_decay: float = 0.7) -> None:
        self.velocity_frames = velocity_frames
        self.coast_decay = coast_decay
        self.last_pose: np.ndarray | None = None
        self.last_stamp: float | None = None
        self.good_pose: np.ndarray | None = None
        self.good_stamp: float | None = None
        self.velocity = np.eye(4)  # relative motion per nominal frame, camera frame
        self.recent: list[np.ndarray] = []  # (6,) rotation vector + translation per tracked frame
        self.frame_dt = NOMINAL_FRAME_DT
        self.lost_frames = 0

    def predict(self, stamp: float) -> np.ndarray:
        """Constant-velocity prediction of the camera-to-world pose at ``stamp``."""
        if self.last_pose is None:
            return np.eye(4)
        frames = (stamp - self.last_stamp) / self.frame_dt if stamp > self.last_stamp else 1.0
        return self.last_pose @ scale_motion(self.velocity, frames)

    def restart(self, pose: np.ndarray, stamp: float) -> None:
        """A new map starts at ``pose``: no motion known yet."""
        self.good_pose, self.good_stamp = pose, stamp
        self.velocity = np.eye(4)
        self.recent = []
        self.lost_frames = 0

    def tracked(self, stamp: float, pose: np.ndarray) -> None:
        """A measured pose. The velocity is the mean of the last few frame-to-frame motions (one frame's
        motion is as noisy as two poses); after a loss it restarts at zero, because the motion across
        the gap says little about the motion now."""
        if self.lost_frames > 0:
            self.recent = []
        elif self.good_pose is not None and stamp > self.good_stamp:
            elapsed = stamp - self.good_stamp
            self.frame_dt = min(max(elapsed, 1e-3), 1.0)
            motion = invert_pose(self.good_pose) @ pose
            twist = np.concatenate([so3_log(motion[:3, :3]), motion[:3, 3]])
            self.recent = [*self.recent, twist][-self.velocity_frames:]
        self.velocity = np.eye(4)
        if self.recent:
            mean = np.mean(self.recent, axis=0)
            self.velocity[:3, :3] = so3_exp_batch(mean[:3])
            self.velocity[:3, 3] = mean[3:]
        self.good_pose, self.good_stamp = pose, stamp
        self.lost_frames = 0

    def coast(self) -> None:
        """An untracked frame: count it and let the velocity decay."""
        self.lost_frames += 1
        self.velocity = scale_motion(self.velocity, self.coast_decay)

    def prior(self, T_guess: np.ndarray, conf: TrackerConfig) -> MotionPrior | None:
        """The prediction (world-to-camera ``T_guess``) as a Gaussian prior on a pose refinement, widening with
        every untracked frame; None when ``motion_prior_*`` switch it off."""
        if conf.motion_prior_m <= 0 or conf.motion_prior_deg <= 0:
            return None
        scale = 1.0 + self.lost_frames
        return MotionPrior(T_guess, conf.motion_prior_m * scale, np.radians(conf.motion_prior_deg) * scale)

    def implausible_jump(self, predicted: np.ndarray, pose: np.ndarray, conf: TrackerConfig) -> str:
        """Why a measured camera-to-world ``pose`` is too far from the ``predicted`` one ("" when it is not):
        ``max_jump_*`` per frame since the last tracked one."""
        moved, turned = pose_difference(predicted, pose)
        allowed = 1.0 + self.lost_frames
        if moved > conf.max_jump_m * allowed or turned > conf.max_jump_deg * allowed:
            return f"implausible jump from the prediction ({moved:.3f} m, {turned:.1f} deg)"
        return ""

    def correct(self, pose: np.ndarray, stamp: float, new_map: bool = False) -> None:
        """A keyframe job measured camera-to-world ``pose`` for the frame at ``stamp``, some frames ago.
        ``new_map``: that frame started a map, so the model restarts there. Otherwise, while this model is lost,
        the prediction continues from that measured pose rather than from the coasted one."""
        if new_map:
            self.restart(pose, stamp)
            if self.last_stamp is None or self.last_stamp <= stamp:
                self.advance(stamp, pose)
        elif self.lost_frames > 0:
            if self.last_stamp == stamp:
                self.tracked(stamp, pose)
            self.last_pose = pose

    def move_world(self, motion: np.ndarray) -> None:
        """The world frame moved (a loop closed): left-multiply the remembered poses by ``motion``, so that the
        next prediction is in the corrected frame (the velocity, in the camera frame, stays)."""
        if self.last_pose is not None:
            self.last_pose = motion @ self.last_pose
        if self.good_pose is not None:
            self.good_pose = motion @ self.good_pose

    def advance(self, stamp: float, pose: np.ndarray) -> None:
        """Remember the pose reported for this frame, tracked or coasted."""
        self.last_pose, self.last_stamp = pose, stamp
