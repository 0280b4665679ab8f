"""The YOLO core: letterbox, both output layouts, class-aware NMS, and real detections on real frames."""

from __future__ import annotations

import numpy as np
import pytest

from twohr.config import YoloConfig
from twohr.errors import ModelError
from twohr.models import BACKENDS, WHAT_IT_NEEDS, available_backends
from twohr.synthetic import SyntheticScene, SyntheticSpec, camera_path
from twohr_services.yolo.core import (
    PAD_VALUE,
    YoloDetector,
    box_iou,
    decode_yolov5,
    decode_yolov8,
    letterbox,
    nms,
    parse_class_names,
    unletterbox_boxes,
)
from twohr_services.yolo.dynamics import load_dynamics_table

# ----------------------------------------------------------------------------- pure functions


def test_letterbox_pads_with_114_and_boxes_map_back():
    rgb = np.full((480, 640, 3), 7, np.uint8)
    canvas, geometry = letterbox(rgb, 320)
    assert canvas.shape == (320, 320, 3)
    assert geometry.scale == 0.5 and geometry.pad_x == 0 and geometry.pad_y == 40
    assert (canvas[:40] == PAD_VALUE).all() and (canvas[280:] == PAD_VALUE).all()
    assert (canvas[40:280] == 7).all()
    # a box in network pixels maps back to the original image, and is clipped there
    boxes = np.array([[10, 50, 110, 90], [-20, 0, 400, 400]], np.float32)
    back = unletterbox_boxes(boxes, geometry, 640, 480)
    np.testing.assert_allclose(back[0], [20, 20, 220, 100])
    np.testing.assert_allclose(back[1], [0, 0, 640, 480])


def test_letterbox_reuses_the_buffer_and_rewrites_padding():
    out = np.zeros((320, 320, 3), np.uint8)
    tall = np.full((400, 200, 3), 9, np.uint8)
    canvas, geometry = letterbox(tall, 320, out=out)
    assert canvas is out
    assert geometry.pad_x == 80 and geometry.pad_y == 0
    assert (out[:, :80] == PAD_VALUE).all() and (out[:, 240:] == PAD_VALUE).all() and (out[:, 80:240] == 9).all()


def _yolov8_tensor(anchors: list[tuple[float, float, float, float, int, float]], classes: int = 80) -> np.ndarray:
    """[1, 4+classes, N] with one (cx, cy, w, h, class, score) per anchor; other class scores are small."""
    out = np.full((1, 4 + classes, len(anchors)), 0.01, np.float32)
    for i, (cx, cy, w, h, cls, score) in enumerate(anchors):
        out[0, :4, i] = cx, cy, w, h
        out[0, 4 + cls, i] = score
    return out


def test_decode_yolov8_layout():
    output = _yolov8_tensor([(100, 100, 40, 80, 0, 0.9), (50, 50, 10, 10, 5, 0.2), (200, 150, 60, 20, 56, 0.6)])
    boxes, scores, class_ids = decode_yolov8(output, conf_threshold=0.25)
    assert class_ids.tolist() == [0, 56]
    np.testing.assert_allclose(scores, [0.9, 0.6], rtol=1e-6)
    np.testing.assert_allclose(boxes, [[80, 60, 120, 140], [170, 140, 230, 160]])


def test_decode_yolov5_layout_multiplies_objectness():
    output = np.zeros((1, 3, 85), np.float32)
    output[0, 0, :5] = 100, 100, 40, 80, 0.9  # person: 0.9 * 0.8 = 0.72
    output[0, 0, 5 + 0] = 0.8
    output[0, 1, :5] = 50, 60, 20, 20, 0.2  # confident class, weak objectness: dropped
    output[0, 1, 5 + 3] = 0.99
    output[0, 2, :5] = 300, 200, 10, 30, 0.6  # chair: 0.6 * 0.5 = 0.3
    output[0, 2, 5 + 56] = 0.5
    boxes, scores, class_ids = decode_yolov5(output, conf_threshold=0.25)
    assert class_ids.tolist() == [0, 56]
    np.testing.assert_allclose(scores, [0.72, 0.3], rtol=1e-6)
    np.testing.assert_allclose(boxes, [[80, 60, 120, 140], [295, 185, 305, 215]])


@pytest.mark.parametrize("decode,shape", [(decode_yolov8, (84,)), (decode_yolov8, (1, 3, 84, 5)),
                                          (decode_yolov5, (1, 10, 4)), (decode_yolov5, (2, 10, 85, 1))])
def test_decoders_reject_wrong_layouts(decode, shape):
    with pytest.raises(ValueError, match="output must be"):
        decode(np.zeros(shape, np.float32), 0.25)


def test_nms_is_class_aware():
    boxes = np.array([[0, 0, 100, 100], [5, 5, 105, 105], [2, 2, 102, 102], [300, 300, 350, 350]], np.float32)
    scores = np.array([0.9, 0.8, 0.7, 0.6], np.float32)
    class_ids = np.array([0, 56, 0, 0])
    keep = nms(boxes, scores, class_ids, iou_threshold=0.45)
    # the chair overlapping the person survives; the second, weaker person box on the same spot does not
    assert keep.tolist() == [0, 1, 3]
    assert box_iou(boxes[0], boxes[1:2])[0] > 0.8
    # with one class, the overlapping box is suppressed
    assert nms(boxes, scores, np.zeros(4, int), 0.45).tolist() == [0, 3]
    assert nms(boxes, scores, class_ids, 0.45, max_detections=2).tolist() == [0, 1]
    assert nms(np.zeros((0, 4)), np.zeros(0), np.zeros(0, int), 0.45).tolist() == []


def test_class_names_come_from_metadata():
    names = parse_class_names({"names": "{0: 'person', 1: 'bicycle', 2: 'dining table'}"})
    assert names == ["person", "bicycle", "dining table"]
    with pytest.raises(ModelError, match="names"):
        parse_class_names({})
    with pytest.raises(ModelError, match="not a class table"):
        parse_class_names({"names": "person, bicycle"})


# ----------------------------------------------------------------------------- real model, real frames


@pytest.mark.parametrize("model", ["yolov8n_320", "yolov5n_320"])
def test_model_metadata_and_input_size(yolo_detector, model):
    detector = yolo_detector(model)
    assert detector.input_size == 320
    assert len(detector.names) == 80
    assert detector.names[0] == "person" and detector.names[60] == "dining table" and detector.names[62] == "tv"


@pytest.mark.parametrize("index,people", [(300, 2), (445, 3)])
def test_frames_with_people_give_person_boxes(yolo_detector, dev_frames, index, people):
    frame = dev_frames(index)
    detections = yolo_detector("yolov8n_320").detect(frame.rgb)
    person = np.array([n == "person" for n in detections.names])
    assert person.sum() >= people
    boxes = detections.boxes[person]
    # people in these frames stand in the room, close to the camera: tall boxes, inside the image
    assert (boxes[:, 3] - boxes[:, 1] > 300).sum() >= people
    assert (boxes[:, [0, 2]] >= 0).all() and (boxes[:, [0, 2]] <= 640).all()
    assert (boxes[:, [1, 3]] >= 0).all() and (boxes[:, [1, 3]] <= 480).all()
    assert detections.scores[person].max() > 0.7


def test_both_layouts_find_the_same_people(yolo_detector, dev_frames):
    rgb = dev_frames(300).rgb
    v8, v5 = yolo_detector("yolov8n_320").detect(rgb), yolo_detector("yolov5n_320").detect(rgb)
    v8_people = v8.boxes[np.array(v8.names) == "person"]
    v5_people = v5.boxes[np.array(v5.names) == "person"]
    assert len(v8_people) == len(v5_people) == 2
    for box in v8_people:
        assert box_iou(box, v5_people).max() > 0.8


def test_room_without_people_has_no_person(yolo_detector, dev_frames):
    detections = yolo_detector("yolov8n_320").detect(dev_frames(100).rgb)
    assert "person" not in detections.names
    assert "chair" in detections.names  # the detector does see the room's furniture


def test_static_synthetic_image_has_no_dynamic_objects(yolo_detector):
    """A rendered room without occluders (what the static_synthetic_sequence fixture holds) has no person,
    nor any other class of the dynamics table."""
    table = load_dynamics_table()
    spec = SyntheticSpec(frames=30, occluders=0, seed=3)
    scene, path = SyntheticScene(spec), camera_path(spec)
    for index in (0, 15):
        rgb, _, dynamic = scene.render(path.poses[index], path.stamps[index] - spec.start_stamp)
        assert not dynamic.any()
        for model in ("yolov8n_320", "yolov5n_320"):
            detections = yolo_detector(model).detect(rgb)
            assert [n for n in detections.names if table.level_of(n)] == []


def test_detector_input_errors():
    with pytest.raises(ModelError, match="unknown model"):
        YoloDetector(YoloConfig(model="yolov99"))
    with pytest.raises(ModelError, match="not a YOLO detector"):
        YoloDetector(YoloConfig(model="faster2d2_WASF_N16"))


def test_detect_rejects_bad_images(yolo_detector):
    detector = yolo_detector("yolov8n_320")
    with pytest.raises(ValueError, match="RGB uint8"):
        detector.detect(np.zeros((480, 640), np.uint8))
    with pytest.raises(ValueError, match="RGB uint8"):
        detector.detect(np.zeros((480, 640, 3), np.float32))


@pytest.mark.parametrize("backend", BACKENDS[1:])
def test_every_backend_finds_the_same_people(dev_frames, backend):
    """The CPU and GPU backends (``yolo.backend``) agree with onnxruntime on the CPU, run where the machine has them."""
    if backend not in available_backends():
        pytest.skip(f"{backend} is not available here: it needs {WHAT_IT_NEEDS[backend]}")
    rgb = dev_frames(300).rgb
    reference = YoloDetector(YoloConfig(model="yolov8n_320", backend="onnxruntime")).detect(rgb)
    detections = YoloDetector(YoloConfig(model="yolov8n_320", backend=backend, precision="f32")).detect(rgb)
    people = detections.boxes[np.array(detections.names) == "person"]
    expected = reference.boxes[np.array(reference.names) == "person"]
    assert len(people) == len(expected) == 2
    for box in people:
        assert box_iou(box, expected).max() > 0.95
