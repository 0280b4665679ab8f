"""The YOLO core: COCO object detection with onnxruntime. RGB image in, :class:`Detections` out.

Pipeline of :meth:`YoloDetector.detect` (paper §3.2):

1. :func:`letterbox` the image into the square network input (aspect ratio kept, pad value 114);
2. run the network: YOLOv8 gives ``[1, 84, N]`` (cx, cy, w, h, 80 class scores, no objectness),
   YOLOv5 gives ``[1, N, 85]`` (cx, cy, w, h, objectness, 80 class scores);
3. :func:`decode_yolov8` / :func:`decode_yolov5` turn that into boxes, scores and class ids;
4. class-aware :func:`nms`, then the boxes are mapped back to original-image pixels.

Class names come from the ONNX metadata (``names``), the layout from the model's registered kind.
"""

from __future__ import annotations

import ast
import threading
from dataclasses import dataclass
from functools import cache

import cv2
import numpy as np

from twohr.config import YoloConfig
from twohr.errors import ModelError
from twohr.features import Detections
from twohr.models import Network, get_spec, model_path

PAD_VALUE = 114
YOLO_KINDS = ("yolov8", "yolov5")


# ----------------------------------------------------------------------------- pure functions


@dataclass(frozen=True)
class Letterbox:
    """How an image was placed in the network input: ``input = image * scale + (pad_x, pad_y)``."""

    scale: float
    pad_x: int
    pad_y: int


def letterbox_geometry(width: int, height: int, size: int) -> tuple[Letterbox, tuple[int, int]]:
    """Scale and padding that fit a ``width`` x ``height`` image centred into a ``size`` square,
    and the resized image size (w, h)."""
    scale = min(size / width, size / height)
    new_w, new_h = min(size, round(width * scale)), min(size, round(height * scale))
    return Letterbox(scale, (size - new_w) // 2, (size - new_h) // 2), (new_w, new_h)


def letterbox(rgb: np.ndarray, size: int, out: np.ndarray | None = None) -> tuple[np.ndarray, Letterbox]:
    """The image resized to fit a ``size`` x ``size`` square, centred and padded with 114.

    Returns the (size, size, 3) uint8 input and the placement; ``out`` is reused when given."""
    height, width = rgb.shape[:2]
    geometry, (new_w, new_h) = letterbox_geometry(width, height, size)
    canvas = out if out is not None else np.empty((size, size, 3), np.uint8)
    canvas[...] = PAD_VALUE
    resized = rgb if (new_w, new_h) == (width, height) else cv2.resize(
        rgb, (new_w, new_h), interpolation=cv2.INTER_LINEAR)
    canvas[geometry.pad_y:geometry.pad_y + new_h, geometry.pad_x:geometry.pad_x + new_w] = resized
    return canvas, geometry


def unletterbox_boxes(boxes: np.ndarray, geometry: Letterbox, width: int, height: int) -> np.ndarray:
    """Boxes x1 y1 x2 y2 from network-input pixels back to original-image pixels, clipped to the image."""
    out = boxes.astype(np.float32, copy=True)
    out[:, [0, 2]] = (out[:, [0, 2]] - geometry.pad_x) / geometry.scale
    out[:, [1, 3]] = (out[:, [1, 3]] - geometry.pad_y) / geometry.scale
    out[:, [0, 2]] = out[:, [0, 2]].clip(0, width)
    out[:, [1, 3]] = out[:, [1, 3]].clip(0, height)
    return out


def _xywh_to_xyxy(xywh: np.ndarray) -> np.ndarray:
    half = xywh[:, 2:4] / 2
    return np.concatenate([xywh[:, :2] - half, xywh[:, :2] + half], axis=1).astype(np.float32)


def decode_yolov8(output: np.ndarray, conf_threshold: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decode a YOLOv8 head ``[1, 4+C, N]`` (or ``[4+C, N]``): rows cx, cy, w, h, then C class scores.

    Returns boxes (M, 4) x1 y1 x2 y2 in input pixels, scores (M,) and class ids (M,) of the anchors
    whose best class score is at least ``conf_threshold``; one class per anchor."""
    pred = np.asarray(output)
    if pred.ndim == 3 and pred.shape[0] == 1:
        pred = pred[0]
    if pred.ndim != 2 or pred.shape[0] < 5:
        raise ValueError(f"YOLOv8 output must be [1, 4+classes, N], got shape {np.shape(output)}")
    class_scores = pred[4:]
    class_ids = class_scores.argmax(axis=0)
    scores = class_scores[class_ids, np.arange(pred.shape[1])]
    keep = scores >= conf_threshold
    return _xywh_to_xyxy(pred[:4, keep].T), scores[keep].astype(np.float32), class_ids[keep].astype(np.int64)


def decode_yolov5(output: np.ndarray, conf_threshold: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decode a YOLOv5 head ``[1, N, 5+C]`` (or ``[N, 5+C]``): cx, cy, w, h, objectness, then C class scores.

    The score is objectness x best class score, as YOLOv5 computes it; returns (boxes, scores, class ids)
    like :func:`decode_yolov8`."""
    pred = np.asarray(output)
    if pred.ndim == 3 and pred.shape[0] == 1:
        pred = pred[0]
    if pred.ndim != 2 or pred.shape[1] < 6:
        raise ValueError(f"YOLOv5 output must be [1, N, 5+classes], got shape {np.shape(output)}")
    pred = pred[pred[:, 4] >= conf_threshold]  # objectness bounds the score: a cheap early cut
    class_ids = pred[:, 5:].argmax(axis=1)
    scores = pred[:, 4] * pred[np.arange(len(pred)), 5 + class_ids]
    keep = scores >= conf_threshold
    return _xywh_to_xyxy(pred[keep, :4]), scores[keep].astype(np.float32), class_ids[keep].astype(np.int64)


def box_iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """IoU of one box x1 y1 x2 y2 against each of ``boxes`` (N, 4)."""
    x1 = np.maximum(box[0], boxes[:, 0])
    y1 = np.maximum(box[1], boxes[:, 1])
    x2 = np.minimum(box[2], boxes[:, 2])
    y2 = np.minimum(box[3], boxes[:, 3])
    inter = np.clip(x2 - x1, 0, None) * np.clip(y2 - y1, 0, None)
    area = (box[2] - box[0]) * (box[3] - box[1])
    areas = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    return inter / np.maximum(area + areas - inter, 1e-9)


def nms(boxes: np.ndarray, scores: np.ndarray, class_ids: np.ndarray, iou_threshold: float,
        max_detections: int = 300) -> np.ndarray:
    """Class-aware greedy non-maximum suppression: indices of kept boxes, best score first.

    A box suppresses only lower-scoring boxes of its own class that overlap it by more than ``iou_threshold``."""
    boxes = np.asarray(boxes, np.float32).reshape(-1, 4)
    if len(boxes) == 0:
        return np.zeros(0, np.int64)
    # shift each class into its own region of the plane, so that boxes of different classes never overlap
    offset = np.asarray(class_ids, np.float32)[:, None] * (float(np.abs(boxes).max()) + 1.0)
    shifted = boxes + offset
    order = np.argsort(-np.asarray(scores), kind="stable")
    keep: list[int] = []
    while order.size and len(keep) < max_detections:
        best = order[0]
        keep.append(int(best))
        rest = order[1:]
        order = rest[box_iou(shifted[best], shifted[rest]) <= iou_threshold]
    return np.array(keep, np.int64)


def parse_class_names(metadata: dict[str, str]) -> list[str]:
    """Class names from an Ultralytics ONNX metadata map, whose ``names`` is a dict literal ``{0: 'person', ...}``."""
    raw = metadata.get("names")
    if raw is None:
        raise ModelError("the YOLO model has no 'names' metadata; export it with Ultralytics' exporter")
    try:
        names = ast.literal_eval(raw)
    except (ValueError, SyntaxError):
        raise ModelError(f"the YOLO model's 'names' metadata is not a class table: {raw[:80]!r}") from None
    if isinstance(names, dict):
        return [str(names[k]) for k in sorted(names)]
    if isinstance(names, list | tuple):
        return [str(n) for n in names]
    raise ModelError(f"the YOLO model's 'names' metadata is not a class table: {raw[:80]!r}")


# ----------------------------------------------------------------------------- network


@cache
def _onnx_header(path: str) -> tuple[list, dict[str, str]]:
    """The ONNX file's input shape and metadata (the class names live there), whichever backend runs it."""
    import onnx

    model = onnx.load(path, load_external_data=False)
    dims = model.graph.input[0].type.tensor_type.shape.dim
    shape = [d.dim_value if d.HasField("dim_value") else d.dim_param for d in dims]
    return shape, {p.key: p.value for p in model.metadata_props}


def check_image(rgb: np.ndarray) -> None:
    """Raise ValueError unless ``rgb`` is an (H, W, 3) uint8 image."""
    if not isinstance(rgb, np.ndarray) or rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        shape = getattr(rgb, "shape", None)
        raise ValueError(f"expected an RGB uint8 image of shape (H, W, 3), got {shape} {getattr(rgb, 'dtype', '')}")


class YoloDetector:
    """COCO detections from a registered YOLOv8 or YOLOv5 ONNX model.

    One onnxruntime session per process, model and thread count; the letterbox canvas and the
    input tensor are reused between calls (a lock makes ``detect`` safe across threads)."""

    default_conf = YoloConfig()

    def __init__(self, conf: YoloConfig | None = None) -> None:
        self.conf = conf or self.default_conf
        spec = get_spec(self.conf.model)
        if spec.kind not in YOLO_KINDS:
            raise ModelError(f"model {spec.name!r} is a {spec.kind} model, not a YOLO detector "
                             f"({' or '.join(YOLO_KINDS)}); choose yolov8n_320, yolov8n, yolov5n_320 or yolov5n")
        self.kind = spec.kind
        path = str(model_path(self.conf.model))
        self.network = Network(path, self.conf.threads, self.conf.backend, self.conf.precision)
        self.input_name = self.network.input_names[0]
        shape, metadata = _onnx_header(path)
        size = shape[2]
        if not isinstance(size, int) or shape[3] != size:
            raise ModelError(f"model {spec.name!r} needs a fixed square input, has {shape}")
        self.input_size = size
        self.names = parse_class_names(metadata)
        self._canvas = np.empty((size, size, 3), np.uint8)
        self._tensor = np.empty((1, 3, size, size), np.float32)
        self._lock = threading.Lock()

    def raw_output(self, rgb: np.ndarray) -> tuple[np.ndarray, Letterbox]:
        """The network's raw head output for an image, and where the image sits in the input."""
        check_image(rgb)
        with self._lock:
            canvas, geometry = letterbox(rgb, self.input_size, out=self._canvas)
            np.multiply(canvas.transpose(2, 0, 1), np.float32(1 / 255), out=self._tensor[0])
            output = self.network({self.input_name: self._tensor})[self.network.output_names[0]].copy()
        return output, geometry

    def detect(self, rgb: np.ndarray) -> Detections:
        """All detections of an RGB uint8 image above ``conf_threshold``, after class-aware NMS, in image pixels."""
        output, geometry = self.raw_output(rgb)
        decode = decode_yolov8 if self.kind == "yolov8" else decode_yolov5
        boxes, scores, class_ids = decode(output, self.conf.conf_threshold)
        keep = nms(boxes, scores, class_ids, self.conf.iou_threshold, self.conf.max_detections)
        height, width = rgb.shape[:2]
        boxes = unletterbox_boxes(boxes[keep], geometry, width, height)
        class_ids = class_ids[keep]
        return Detections(boxes, scores[keep], class_ids, [self.names[c] for c in class_ids])
