"""``twohr run --view``: the in-process pipeline on a Foxglove live view, as the gateway shows a session.

Composition root, like :mod:`twohr_app.pipeline`: it reads the pipeline's per-frame results and hands
them to the shared converter (:mod:`twohr.foxglove_convert`) and server (:class:`twohr.foxglove_live.LiveView`).
"""

from __future__ import annotations

from twohr.dataset import Frame, RGBDSequence
from twohr.foxglove_live import LiveView
from twohr.geometry import rot_to_quat
from twohr_services.tracker.schedule import Schedule
from twohr_services.tracker.stages import FrameStats
from twohr_services.tracker.trajectory import TrackResult


class PipelineLiveView:
    """An ``on_frame`` callback for :func:`~twohr_app.pipeline.run_sequence` that streams each frame's image,
    tracked keypoints, dynamic mask, pose, path and (when a keyframe changed it) the map to a :class:`LiveView`."""

    def __init__(self, sequence: RGBDSequence, host: str = "127.0.0.1", port: int = 8765,
                 robot_id: str = "run") -> None:
        self.view = LiveView(host, port, jpeg_quality=None)
        self.view.advertise(robot_id)
        self.sequence, self.robot_id = sequence, robot_id
        self.map_sent = -1

    def __call__(self, frame: Frame, result: TrackResult, stats: FrameStats, schedule: Schedule) -> None:
        convert, robot, t = self.view.converter, self.robot_id, frame.stamp
        # the colour image's own file, as the source sends it: no encoding on the per-frame path
        path = self.sequence.records[frame.index].rgb_path
        image = convert.frame(robot, t, self.sequence.camera, encoded=path.read_bytes(),
                              encoding="png" if path.suffix.lower() == ".png" else "jpeg")
        messages = [*image,
                    *convert.pose(robot, t, result.pose[:3, 3], rot_to_quat(result.pose[:3, :3]))]
        if result.observed_xy is not None:
            messages += convert.keypoints(robot, t, result.observed_xy)
        if schedule.mask is not None:
            messages += convert.dynamic_mask(robot, t, schedule.mask)
        snapshot = schedule.map_snapshot(since=self.map_sent)
        if snapshot is not None and len(snapshot.points):
            self.map_sent = snapshot.version
            messages += convert.landmarks(robot, t, snapshot.points)
        self.view.log(messages)

    def close(self) -> None:
        self.view.close()
