"""The yolo service: ``twohr/<robot>/frames`` in, ``twohr/<robot>/dynamics`` (detections + mask) out."""

from __future__ import annotations

import time

import numpy as np

from twohr import keys
from twohr.messages import ControlMsg, DynamicsMsg, FrameMsg, decode, encode
from twohr.service import Service, serve

from .masks import DynamicMasker


class YoloService(Service):
    """Dynamic-object masks for every frame; one stateful masker per session (detection every n-th frame)."""

    name = "yolo"
    follows_sessions = True

    def __init__(self, bus=None) -> None:
        super().__init__(bus, queue_size=4, policy="drop_oldest")
        self.maskers: dict[str, DynamicMasker] = {}

    def subscriptions(self) -> list[str]:
        return [keys.all_robots("frames")]

    def on_session_start(self, control: ControlMsg) -> None:
        self.maskers[control.session_id] = DynamicMasker(control.config.yolo)

    def on_session_stop(self, session_id: str) -> None:
        self.maskers.pop(session_id, None)

    def handle(self, key: str, payload: bytes) -> None:
        frame, arrays = decode(payload, FrameMsg)
        masker = self.maskers.get(frame.session_id)
        if masker is None:
            masker = self.maskers[frame.session_id] = DynamicMasker(self.config_for(frame.session_id).yolo)
        depth = arrays["depth"].astype(np.float32) / np.float32(frame.camera.depth_factor)
        t0 = time.perf_counter()
        regions = masker(arrays["rgb"], depth)
        elapsed = (time.perf_counter() - t0) * 1000
        dyn = regions.dynamic
        out = DynamicsMsg(session_id=frame.session_id, robot_id=frame.robot_id, frame_index=frame.frame_index,
                          stamp=frame.stamp, names=list(dyn.names), levels=list(masker.conf.remove_levels),
                          elapsed_ms=elapsed, sent_at=frame.sent_at)
        arrays_out = {"boxes": dyn.boxes.astype(np.float32), "scores": dyn.scores.astype(np.float32),
                      "class_ids": dyn.class_ids.astype(np.int64), "mask": regions.mask.astype(np.uint8)}
        self.publish(keys.key(frame.robot_id, "dynamics"), encode(out, arrays_out, {"mask": "png"}))


def main(argv: list[str] | None = None) -> None:
    serve(YoloService, argv)
