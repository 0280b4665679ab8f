"""Dynamic-region masks and the keypoint filter, on cases with a known answer, and mask propagation on real frames."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from twohr.config import YoloConfig
from twohr.features import Detections, Keypoints
from twohr.synthetic import SyntheticScene, SyntheticSpec, camera_path
from twohr_services.yolo.masks import (
    DynamicMasker,
    box_mask,
    depth_refined_mask,
    filter_keypoints,
    grow_border,
    grow_boxes,
    object_depth,
)


def _detections(*boxes: list[float], name: str = "person") -> Detections:
    n = len(boxes)
    return Detections(np.array(boxes, np.float32).reshape(n, 4), np.full(n, 0.9, np.float32),
                      np.zeros(n, np.int64), [name] * n)


def _person_scene() -> tuple[np.ndarray, np.ndarray, np.ndarray, list[float]]:
    """Depth (H, W) of a person-shaped blob at ~2 m in front of a wall at 4.5 m, the blob's exact pixels,
    a loose detector-like box around it, and the pixels of a table beside the person at the same depth."""
    height, width = 240, 320
    person = np.zeros((height, width), np.uint8)
    cv2.circle(person, (160, 45), 18, 1, -1)  # head
    cv2.rectangle(person, (135, 62), (185, 140), 1, -1)  # torso
    cv2.rectangle(person, (112, 60), (134, 125), 1, -1)  # an arm held out sideways
    cv2.rectangle(person, (136, 141), (153, 215), 1, -1)  # legs, apart
    cv2.rectangle(person, (170, 141), (187, 215), 1, -1)
    person = person.astype(bool)
    rows = np.arange(height, dtype=np.float32)[:, None]
    depth = np.full((height, width), 4.5, np.float32)
    depth[person] = (1.9 + 0.001 * rows * np.ones((1, width), np.float32))[person]  # a slight lean
    depth[:, 200:230] = np.where(rows >= 150, 2.0, depth[:, 200:230])  # a table top beside the legs
    table = np.zeros_like(person)
    table[150:, 200:230] = True
    # an IR shadow: no reading along the person's right edge, and a frame of missing depth at the border
    shadow = cv2.dilate(person.astype(np.uint8), np.ones((1, 9), np.uint8)).astype(bool) & ~person
    shadow[:, :150] = False
    depth[shadow] = 0
    depth[:, :6] = 0
    depth[:3] = 0
    return depth, person, table, [95.0, 15.0, 235.0, 225.0]


def test_depth_refined_mask_is_smaller_than_its_box_and_holds_the_person():
    depth, person, table, box = _person_scene()
    detections = _detections(box)
    boxed = box_mask(detections, depth.shape)
    refined = depth_refined_mask(detections, depth, margin=0, band=0.5)
    assert refined[person].all(), "every person pixel must stay masked"
    assert refined.sum() < 0.6 * boxed.sum()
    assert not (refined & ~boxed).any()
    # the wall between the legs and beside the body is freed, the IR shadow at the body's edge is not
    assert not refined[160:215, 159:165].any()
    assert not refined[20:40, 100:140].any()
    assert refined[(depth == 0) & boxed & (np.arange(depth.shape[1]) > 185)].all()
    # a table at the person's depth that does not touch them is not part of the person
    assert not refined[table & boxed].any()
    assert abs(object_depth(depth, np.array(box)) - 2.0) < 0.1


def test_depth_refined_mask_with_margin_stays_in_the_dilated_box():
    depth, person, _, box = _person_scene()
    detections = _detections(box)
    refined = depth_refined_mask(detections, depth, margin=6, band=0.5)
    tight = depth_refined_mask(detections, depth, margin=0, band=0.5)
    assert refined[tight].all() and refined.sum() > tight.sum()
    assert not (refined & ~box_mask(detections, depth.shape, margin=6)).any()


def test_box_without_depth_in_its_centre_is_masked_whole():
    depth = np.zeros((100, 100), np.float32)
    detections = _detections([20, 20, 60, 80])
    np.testing.assert_array_equal(depth_refined_mask(detections, depth, margin=2), box_mask(detections, (100, 100), 2))


def test_depth_refined_mask_on_a_rendered_occluder():
    """twohr.synthetic renders the occluder's pixels exactly: a loose box around them must give a mask
    that keeps all of them and frees most of the room behind."""
    spec = SyntheticSpec(frames=60)
    scene, path = SyntheticScene(spec), camera_path(spec)
    for index in (10, 20):
        _, depth, truth = scene.render(path.poses[index], path.stamps[index] - spec.start_stamp)
        ys, xs = np.nonzero(truth)
        slack = 0.15 * (xs.max() - xs.min())
        box = [xs.min() - slack, ys.min() - slack, xs.max() + 1 + slack, ys.max() + 1 + slack]
        detections = _detections(box)
        boxed = box_mask(detections, truth.shape)
        refined = depth_refined_mask(detections, depth.astype(np.float32), margin=0, band=0.5)
        background = boxed & ~truth
        assert truth.sum() > 0.1 * truth.size and background.sum() > 0.2 * boxed.sum()  # a real test case
        assert refined[truth].all()
        assert refined.sum() < boxed.sum()
        assert (refined & background).sum() < 0.1 * background.sum()


def test_box_mask_margin_and_clipping():
    detections = _detections([10, 20, 30, 60], [90, 0, 120, 10])
    mask = box_mask(detections, (100, 100), margin=0)
    assert mask.sum() == 20 * 40 + 10 * 10
    grown = box_mask(detections, (100, 100), margin=5)
    assert grown.sum() == 30 * 50 + 15 * 15
    assert box_mask(Detections.empty(), (10, 10), 3).sum() == 0


def test_filter_keypoints_removes_the_ones_inside():
    mask = np.zeros((100, 200), bool)
    mask[20:60, 50:120] = True
    xy = np.array([[10, 10], [50, 20], [119.4, 59.4], [119.6, 30], [80, 40], [250, 40], [-5, 30]], np.float32)
    keypoints = Keypoints(xy, np.eye(7, 128, dtype=np.float32), np.arange(7, dtype=np.float32))
    kept, removed = filter_keypoints(keypoints, mask)
    assert removed.tolist() == [False, True, True, False, True, False, False]
    assert len(kept) == 4
    np.testing.assert_array_equal(kept.scores, [0, 3, 5, 6])
    np.testing.assert_array_equal(kept.descriptors, keypoints.descriptors[~removed])
    empty, none_removed = filter_keypoints(Keypoints.empty(), mask)
    assert len(empty) == 0 and none_removed.shape == (0,)


def test_grow_border_grows_only_regions_at_the_border():
    mask = np.zeros((100, 100), bool)
    mask[30:60, 0:20] = True  # touches the left border
    mask[40:50, 60:70] = True  # interior
    grown = grow_border(mask, grow_px=5)
    assert grown[mask].all()
    assert grown[30:60, 20:25].all() and grown[25, 5]
    assert not grown[40:50, 71:80].any() and not grown[35:40, 60:70].any()
    np.testing.assert_array_equal(grow_border(mask, 0), mask)


def test_grow_boxes_in_proportion_to_frames_elapsed():
    detections = _detections([100, 50, 200, 350])
    two = grow_boxes(detections, frames_elapsed=2, growth=0.05, shape=(480, 640))
    np.testing.assert_allclose(two.boxes[0], [90, 40, 210, 360])
    assert grow_boxes(detections, 0, 0.05, (480, 640)).boxes is detections.boxes
    clipped = grow_boxes(detections, frames_elapsed=20, growth=0.1, shape=(480, 640))
    np.testing.assert_allclose(clipped.boxes[0], [0, 0, 400, 480])


def test_every_nth_frame_detection_propagates_masks(dev_frames):
    """Detect on frames 300 and 303 only; the masks in between still cover the people that fresh
    detections find there."""
    conf = YoloConfig(every_n=3, mask="box")
    propagating = DynamicMasker(conf)
    fresh = DynamicMasker(conf.model_copy(update={"every_n": 1}), detector=propagating.detector)
    flags, coverage = [], []
    for index in range(300, 306):
        frame = dev_frames(index)
        regions = propagating(frame.rgb, frame.depth)
        truth = fresh(frame.rgb, frame.depth).mask
        flags.append(regions.fresh)
        coverage.append((regions.mask & truth).sum() / truth.sum())
        assert regions.frames_since_detection == (index - 300) % 3
        assert all(n == "person" for n in regions.dynamic.names)
    assert flags == [True, False, False, True, False, False]
    assert min(coverage) > 0.97
    propagating.reset()
    assert propagating(dev_frames(301).rgb).fresh


def test_masker_depth_mode_and_levels(dev_frames):
    frame = dev_frames(300)  # two people and a chair
    depth_masker = DynamicMasker(YoloConfig(mask="depth"))
    regions = depth_masker(frame.rgb, frame.depth)
    boxes = box_mask(regions.dynamic, frame.depth.shape, YoloConfig().box_margin)
    assert 0 < regions.mask.sum() < boxes.sum()
    with pytest.raises(ValueError, match="needs a depth image"):
        depth_masker(frame.rgb)
    with pytest.raises(ValueError, match="depth shape"):
        depth_masker(frame.rgb, frame.depth[:100])
    with_chairs = DynamicMasker(YoloConfig(remove_levels=["high", "medium"], mask="box"),
                                detector=depth_masker.detector)
    names = with_chairs(frame.rgb).dynamic.names
    assert "chair" in names and "person" in names
    disabled = DynamicMasker(YoloConfig(enabled=False))
    assert disabled.detector is None and not disabled(frame.rgb).mask.any()
