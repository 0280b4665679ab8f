"""The detector service: 2HR keypoints for the tracker's schedule.

The tracker asks one replica for a frame's keypoints on ``twohr/<robot>/rpc/detect/<replica>`` (query: the frame
message as the source sent it; reply: the keypoints): for keyframes in the ``keyframes`` schedule, for every frame
in ``every_frame``. Each answer is also published on ``twohr/<robot>/keypoints``, for recordings and views.
"""

from __future__ import annotations

import functools
import time

import numpy as np

from twohr import keys
from twohr.config import DetectorConfig
from twohr.dataset import undistorted
from twohr.messages import ControlMsg, FrameMsg, ImageMsg, KeypointsMsg, MessageError, decode, encode
from twohr.service import MODEL_CACHE_SIZE, Service, reply_to, serve

from .core import build_detector


class DetectorService(Service):
    """2HR keypoints with the detector config of the frame's session."""

    name = "detector"
    priority = "keyframe"  # the map's work: an equal share of the CPU, never less
    follows_sessions = True

    def __init__(self, bus=None) -> None:
        super().__init__(bus, queue_size=4, policy="drop_oldest")
        # one detector per distinct config, shared by sessions; a few at most (each holds a network)
        self.detector_for = functools.lru_cache(maxsize=MODEL_CACHE_SIZE)(
            lambda conf_json: build_detector(DetectorConfig.model_validate_json(conf_json)))

    def subscriptions(self) -> list[str]:
        return []  # queries only

    def on_start(self) -> None:
        self.queryable = self.declare_replica_queryable(keys.DETECT_QUERY)
        self._warm(DetectorConfig())

    def _warm(self, conf: DetectorConfig) -> None:
        conf_json = conf.model_dump_json()

        def compile_for_vga() -> None:
            detector = self.detector_for(conf_json)
            if (640, 480) not in getattr(detector, "input_scales", {}):  # not yet run at this size (OpenCV: none)
                detector.detect(np.zeros((480, 640, 3), np.uint8))

        self.warm_up(f"the {conf.model} network", compile_for_vga)

    def on_session_start(self, control: ControlMsg) -> None:
        """A session with a detector config of its own gets its network compiled now, not on its first keyframe:
        a live camera does not wait, so frames that queue behind a first keyframe are dropped."""
        self._warm(control.config.detector)

    def handle(self, key: str, payload) -> None:
        reply_to(payload, self._keypoints)

    def _keypoints(self, payload: bytes) -> bytes:
        frame, arrays = decode(payload, only=("rgb",))
        if not isinstance(frame, (ImageMsg, FrameMsg)):  # a keyframe's colour image, or its whole frame
            raise MessageError(f"the detector reads a frame or its image, not {frame.schema_name}")
        detector = self.detector_for(self.config_for(frame.session_id).detector.model_dump_json())
        t0 = time.perf_counter()
        kp = detector.detect(undistorted(arrays["rgb"], frame.camera))
        elapsed = (time.perf_counter() - t0) * 1000
        out = KeypointsMsg(session_id=frame.session_id, robot_id=frame.robot_id, frame_index=frame.frame_index,
                           stamp=frame.stamp, width=frame.camera.width, height=frame.camera.height,
                           elapsed_ms=elapsed, sent_at=frame.sent_at)
        arrays_out = {"xy": kp.xy, "descriptors": kp.descriptors, "scores": kp.scores}
        if kp.reliability is not None:
            arrays_out |= {"reliability": kp.reliability, "repeatability": kp.repeatability}
        data = encode(out, arrays_out)
        self.publish(keys.key(frame.robot_id, "keypoints"), data)
        return data


def main(argv: list[str] | None = None) -> None:
    serve(DetectorService, argv)
