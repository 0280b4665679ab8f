"""The yolo service: dynamic-object detections and masks for the tracker's schedule.

The tracker asks one replica on ``twohr/<robot>/rpc/dynamics/<replica>`` (query: the frame message; reply: that
frame's detections and mask): every few frames and for keyframes in the ``keyframes`` schedule, for every frame in
``every_frame``. Each answer is also published on ``twohr/<robot>/dynamics``, for recordings and views.
"""

from __future__ import annotations

import functools
import time

import numpy as np

from twohr import keys
from twohr.config import YoloConfig
from twohr.dataset import depth_in_metres, undistorted
from twohr.messages import ControlMsg, DynamicsMsg, FrameMsg, decode, encode
from twohr.service import MODEL_CACHE_SIZE, Service, reply_to, serve

from .core import YoloDetector
from .masks import DynamicMasker


class YoloService(Service):
    """Dynamic-object masks; one stateful masker per session."""

    name = "yolo"
    priority = "keyframe"  # the map's work: an equal share of the CPU, never less
    follows_sessions = True

    def __init__(self, bus=None) -> None:
        super().__init__(bus, queue_size=4, policy="drop_oldest")
        self.maskers: dict[str, DynamicMasker] = {}
        # one network per distinct config, shared by the sessions' maskers (each keeps its own stream state)
        self.network_for = functools.lru_cache(maxsize=MODEL_CACHE_SIZE)(
            lambda conf_json: YoloDetector(YoloConfig.model_validate_json(conf_json)))

    def subscriptions(self) -> list[str]:
        return []  # queries only

    def on_start(self) -> None:
        self.queryable = self.declare_replica_queryable(keys.DYNAMICS_QUERY)
        default = YoloConfig()
        self.warm_up(f"the {default.model} network", lambda: self.network_for(default.model_dump_json()).detect(
            np.zeros((480, 640, 3), np.uint8)))

    def _new_masker(self, conf: YoloConfig) -> DynamicMasker:
        return DynamicMasker(conf, self.network_for(conf.model_dump_json()) if conf.enabled else None)

    def on_session_start(self, control: ControlMsg) -> None:
        self.maskers[control.session_id] = self._new_masker(control.config.yolo)

    def on_session_stop(self, session_id: str) -> None:
        self.maskers.pop(session_id, None)

    def _masker(self, session_id: str) -> DynamicMasker:
        if session_id not in self.maskers:
            self.maskers[session_id] = self._new_masker(self.config_for(session_id).yolo)
        return self.maskers[session_id]

    def handle(self, key: str, payload) -> None:
        reply_to(payload, self._dynamics)

    def _dynamics(self, payload: bytes) -> bytes:
        """The dynamic regions of the frame in a query, from the session's masker (``yolo.every_n``: it detects
        on every n-th query and propagates its boxes between), as ``twohr run`` masks its frames."""
        frame, rgb, depth = _frame_images(payload)
        masker = self._masker(frame.session_id)
        t0 = time.perf_counter()
        regions = masker(rgb, depth)
        return self._publish(frame, masker, regions.dynamic, regions.mask, (time.perf_counter() - t0) * 1000)

    def _publish(self, frame: FrameMsg, masker: DynamicMasker, dynamic, mask: np.ndarray, elapsed: float) -> bytes:
        out = DynamicsMsg(session_id=frame.session_id, robot_id=frame.robot_id, frame_index=frame.frame_index,
                          stamp=frame.stamp, names=list(dynamic.names), levels=list(masker.conf.remove_levels),
                          elapsed_ms=elapsed, sent_at=frame.sent_at)
        arrays_out = {"boxes": dynamic.boxes.astype(np.float32), "scores": dynamic.scores.astype(np.float32),
                      "class_ids": dynamic.class_ids.astype(np.int64), "mask": mask.astype(np.uint8)}
        data = encode(out, arrays_out, {"mask": "png"})
        self.publish(keys.key(frame.robot_id, "dynamics"), data)
        return data


def _frame_images(payload: bytes) -> tuple[FrameMsg, np.ndarray, np.ndarray]:
    """A frame message's header, undistorted colour image and depth in metres."""
    frame, arrays = decode(payload, FrameMsg)
    return frame, undistorted(arrays["rgb"], frame.camera), depth_in_metres(arrays["depth"], frame.camera)


def main(argv: list[str] | None = None) -> None:
    serve(YoloService, argv)
