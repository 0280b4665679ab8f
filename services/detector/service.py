"""The detector service: ``twohr/<robot>/frames`` in, ``twohr/<robot>/keypoints`` out."""

from __future__ import annotations

import time

from twohr import keys
from twohr.config import DetectorConfig
from twohr.messages import FrameMsg, KeypointsMsg, decode, encode
from twohr.service import Service, serve

from .core import build_detector


class DetectorService(Service):
    """2HR keypoints for every frame, with the detector config of the frame's session."""

    name = "detector"
    follows_sessions = True

    def __init__(self, bus=None) -> None:
        super().__init__(bus, queue_size=4, policy="drop_oldest")
        self.detectors: dict[str, object] = {}  # one per distinct config, shared by sessions

    def subscriptions(self) -> list[str]:
        return [keys.all_robots("frames")]

    def detector_for(self, conf: DetectorConfig):
        key = conf.model_dump_json()
        if key not in self.detectors:
            self.detectors[key] = build_detector(conf)
        return self.detectors[key]

    def handle(self, key: str, payload: bytes) -> None:
        frame, arrays = decode(payload, FrameMsg)
        detector = self.detector_for(self.config_for(frame.session_id).detector)
        t0 = time.perf_counter()
        kp = detector.detect(arrays["rgb"])
        elapsed = (time.perf_counter() - t0) * 1000
        out = KeypointsMsg(session_id=frame.session_id, robot_id=frame.robot_id, frame_index=frame.frame_index,
                           stamp=frame.stamp, width=frame.camera.width, height=frame.camera.height,
                           elapsed_ms=elapsed, sent_at=frame.sent_at)
        arrays_out = {"xy": kp.xy, "descriptors": kp.descriptors, "scores": kp.scores}
        if kp.reliability is not None:
            arrays_out |= {"reliability": kp.reliability, "repeatability": kp.repeatability}
        self.publish(keys.key(frame.robot_id, "keypoints"), encode(out, arrays_out))


def main(argv: list[str] | None = None) -> None:
    serve(DetectorService, argv)
