"""Front-end outputs kept in memory and shared between runs that differ only after the front end."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from twohr.config import PipelineConfig
from twohr_app.pipeline import FrontEnd, StageOutput


@dataclass
class FrontCache:
    """Front-end outputs (keypoints, dynamic masks and their timings) of every frame in a range, kept in memory
    and shared between runs that differ only after the front end: keypoints by detector config, masks by yolo
    config. The one cache of the in-process studies (ablations, sensitivity, the tracker bench)."""

    keypoints: dict[tuple, dict[int, tuple]] = field(default_factory=dict)
    masks: dict[tuple, dict[int, tuple]] = field(default_factory=dict)

    def outputs(self, sequence, config: PipelineConfig, stop: int, progress: bool, start: int = 0,
                step: int = 1) -> dict[int, StageOutput]:
        """Frame index -> :class:`StageOutput` of frames ``start:stop:step``, running the networks only once."""
        frames = (start, stop, step)
        det_key = (config.detector.model_dump_json(), frames)
        yolo_key = (config.yolo.model_dump_json(), frames) if config.yolo.enabled else None
        need_det = det_key not in self.keypoints
        need_yolo = yolo_key is not None and yolo_key not in self.masks
        if need_det or need_yolo:
            from tqdm import tqdm

            front = FrontEnd(config)
            det, masks = self.keypoints.setdefault(det_key, {}), self.masks.setdefault(yolo_key, {})
            for frame in tqdm(sequence.frames(start, stop, step), total=len(range(start, stop, step)),
                              disable=not progress, unit="frame",
                              desc=f"front end {config.detector.features}{' + yolo' if yolo_key else ''}"):
                if need_det:
                    t0 = time.perf_counter()
                    det[frame.index] = (front.detector.detect(frame.rgb), (time.perf_counter() - t0) * 1000)
                if need_yolo:
                    t0 = time.perf_counter()
                    regions = front.masker(frame.rgb, frame.depth)
                    masks[frame.index] = (regions.mask, len(regions.dynamic), (time.perf_counter() - t0) * 1000)
        out = {}
        for index, (kp, ms_det) in self.keypoints[det_key].items():
            mask, objects, ms_yolo = self.masks[yolo_key][index] if yolo_key else (None, 0, 0.0)
            out[index] = StageOutput(kp, mask, objects, ms_det, ms_yolo)
        return out
