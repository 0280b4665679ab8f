"""JSON Schemas of the Foxglove well-known message types we record, and converters to them.

Foxglove Studio (and Lichtblick) recognise these schema names with JSON encoding, so a
recording opens with images, keypoint and box overlays, poses and transforms ready to view.
"""

from __future__ import annotations

import base64
import json

import numpy as np

_TIME = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
_VEC3 = {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}}
_QUAT = {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}}
_COLOR = {"type": "object", "properties": {k: {"type": "number"} for k in "rgba"}}
_POINT2 = {"type": "object", "properties": {"x": {"type": "number"}, "y": {"type": "number"}}}

SCHEMAS: dict[str, dict] = {
    "foxglove.CompressedImage": {
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "data": {"type": "string", "contentEncoding": "base64"},
            "format": {"type": "string"},
        },
    },
    "foxglove.ImageAnnotations": {
        "type": "object",
        "properties": {
            "circles": {"type": "array", "items": {"type": "object"}},
            "points": {
                "type": "array",
                "items": {
                    "type": "object",
                    "properties": {
                        "timestamp": _TIME,
                        "type": {"type": "integer", "description": "0 unknown, 1 points, 2 line loop, 3 strip, 4 list"},
                        "points": {"type": "array", "items": _POINT2},
                        "outline_color": _COLOR,
                        "outline_colors": {"type": "array", "items": _COLOR},
                        "fill_color": _COLOR,
                        "thickness": {"type": "number"},
                    },
                },
            },
            "texts": {"type": "array", "items": {"type": "object"}},
        },
    },
    "foxglove.PoseInFrame": {
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "pose": {"type": "object", "properties": {"position": _VEC3, "orientation": _QUAT}},
        },
    },
    "foxglove.FrameTransform": {
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "parent_frame_id": {"type": "string"},
            "child_frame_id": {"type": "string"},
            "translation": _VEC3,
            "rotation": _QUAT,
        },
    },
}


def schema_bytes(name: str) -> bytes:
    return json.dumps({"title": name, **SCHEMAS[name]}).encode()


def stamp(seconds: float) -> dict:
    sec = int(np.floor(seconds))
    return {"sec": sec, "nsec": int(round((seconds - sec) * 1e9)) % 1_000_000_000}


def compressed_image(seconds: float, frame_id: str, data: bytes, fmt: str) -> bytes:
    return json.dumps({"timestamp": stamp(seconds), "frame_id": frame_id,
                       "data": base64.b64encode(data).decode(), "format": fmt}).encode()


def keypoint_annotations(seconds: float, xy: np.ndarray) -> bytes:
    points = [{"x": float(x) + 0.5, "y": float(y) + 0.5} for x, y in xy]
    ann = {"timestamp": stamp(seconds), "type": 1, "points": points, "outline_color": {"r": 0, "g": 1, "b": 0, "a": 1},
           "outline_colors": [], "fill_color": {"r": 0, "g": 1, "b": 0, "a": 1}, "thickness": 3.0}
    return json.dumps({"circles": [], "points": [ann], "texts": []}).encode()


def box_annotations(seconds: float, boxes: np.ndarray) -> bytes:
    anns = []
    for x1, y1, x2, y2 in boxes:
        corners = [(x1, y1), (x2, y1), (x2, y2), (x1, y2)]
        points = [{"x": float(x), "y": float(y)} for x, y in corners]
        anns.append({"timestamp": stamp(seconds), "type": 2, "points": points,
                     "outline_color": {"r": 1, "g": 0.2, "b": 0.2, "a": 1}, "outline_colors": [],
                     "fill_color": {"r": 0, "g": 0, "b": 0, "a": 0}, "thickness": 2.0})
    return json.dumps({"circles": [], "points": anns, "texts": []}).encode()


def pose_in_frame(seconds: float, position: list[float], orientation: list[float], frame_id: str = "world") -> bytes:
    return json.dumps({"timestamp": stamp(seconds), "frame_id": frame_id,
                       "pose": {"position": dict(zip("xyz", position, strict=True)),
                                "orientation": dict(zip("xyzw", orientation, strict=True))}}).encode()


def frame_transform(seconds: float, parent: str, child: str, position: list[float], orientation: list[float]) -> bytes:
    return json.dumps({"timestamp": stamp(seconds), "parent_frame_id": parent, "child_frame_id": child,
                       "translation": dict(zip("xyz", position, strict=True)),
                       "rotation": dict(zip("xyzw", orientation, strict=True))}).encode()
