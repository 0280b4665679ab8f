"""Loading real and synthetic TUM-layout sequences, and clear errors on bad input."""

import shutil

import cv2
import numpy as np
import pytest

from twohr.dataset import CAMERA_PRESETS, GT_EXTRINSIC_PRESETS, RGBDSequence, associate_stamps
from twohr.errors import DatasetError
from twohr.geometry import invert_pose
from twohr.trajectory import read_tum


def test_dev_sequence_loads(dev_sequence):
    seq = RGBDSequence(dev_sequence)
    assert len(seq) == 560
    assert seq.camera == CAMERA_PRESETS["bonn"]
    frame = seq.read(0)
    assert frame.rgb.shape == (480, 640, 3) and frame.rgb.dtype == np.uint8
    assert frame.depth.shape == (480, 640) and frame.depth.dtype == np.float32
    valid = frame.depth[frame.depth > 0]
    assert 0.3 < np.median(valid) < 8.0  # metres: the depth factor was applied
    assert seq.default_gt_extrinsic() == "bonn"


def test_association_from_lists_matches_associations_file(dev_sequence, tmp_path):
    seq = RGBDSequence(dev_sequence)
    copy = tmp_path / "rgbd_bonn_copy"
    copy.mkdir()
    for name in ("rgb.txt", "depth.txt"):
        shutil.copy(dev_sequence / name, copy / name)
    (copy / "rgb").symlink_to(dev_sequence / "rgb")
    (copy / "depth").symlink_to(dev_sequence / "depth")
    rebuilt = RGBDSequence(copy)
    assert [r.stamp for r in rebuilt.records] == [r.stamp for r in seq.records]
    assert [r.depth_stamp for r in rebuilt.records] == [r.depth_stamp for r in seq.records]


def test_associate_is_one_to_one_and_windowed():
    pairs = associate_stamps([0.0, 0.01, 1.0], [0.004, 0.5, 1.05], 0.02)
    assert pairs == [(0, 0)]


def test_bonn_extrinsic_is_rigid_with_a_small_lever_arm():
    left, right = GT_EXTRINSIC_PRESETS["bonn"]
    for m in (left, right):
        assert np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-9)
    assert 0.01 < np.linalg.norm(right[:3, 3]) < 0.03


def test_gt_extrinsic_changes_camera_frame(dev_sequence):
    seq = RGBDSequence(dev_sequence)
    raw = seq.ground_truth("none")
    cam = seq.ground_truth("bonn")
    assert len(raw) == len(cam) == len(read_tum(dev_sequence / "groundtruth.txt"))
    left, right = GT_EXTRINSIC_PRESETS["bonn"]
    assert np.allclose(invert_pose(left) @ cam.poses[10] @ invert_pose(right), raw.poses[10])


def test_synthetic_camera_file_and_exact_geometry(synthetic_sequence):
    """A static pixel of frame A, lifted with its depth and moved by GT, lands where frame B sees that depth."""
    seq = RGBDSequence(synthetic_sequence)
    gt = seq.ground_truth()
    k = seq.camera.matrix
    a, b = seq.read(0), seq.read(12)
    dyn_a = cv2.imread(str(synthetic_sequence / "dynamic" / f"{seq.records[0].stamp:.6f}.png"), 0) > 0
    v, u = np.mgrid[20:220:7, 20:300:7]
    u, v = u.ravel(), v.ravel()
    keep = ~dyn_a[v, u]
    u, v = u[keep], v[keep]
    z = a.depth[v, u].astype(np.float64)
    pts = np.stack([(u - k[0, 2]) / k[0, 0] * z, (v - k[1, 2]) / k[1, 1] * z, z, np.ones_like(z)])
    rel = invert_pose(gt.poses[12]) @ gt.poses[0]
    pb = rel @ pts
    ub = k[0, 0] * pb[0] / pb[2] + k[0, 2]
    vb = k[1, 1] * pb[1] / pb[2] + k[1, 2]
    inside = (ub > 1) & (ub < 318) & (vb > 1) & (vb < 238)
    ui, vi = np.round(ub[inside]).astype(int), np.round(vb[inside]).astype(int)
    depth_b = b.depth[vi, ui]
    visible = np.abs(depth_b - pb[2, inside]) < 0.05
    assert inside.sum() > 500
    assert visible.mean() > 0.8  # the rest are occluded by the moving box or at depth edges


def test_missing_folder_is_a_clear_error(tmp_path):
    with pytest.raises(DatasetError, match="sequence folder not found"):
        RGBDSequence(tmp_path / "nope")


def test_unknown_camera_needs_a_file(tmp_path, synthetic_sequence):
    copy = tmp_path / "mystery"
    shutil.copytree(synthetic_sequence, copy)
    (copy / "camera.yaml").unlink()
    with pytest.raises(DatasetError, match="camera.yaml"):
        RGBDSequence(copy)


def test_corrupt_frames_are_skipped_and_counted(tmp_path, synthetic_sequence):
    copy = tmp_path / "corrupt"
    shutil.copytree(synthetic_sequence, copy)
    seq = RGBDSequence(copy)
    seq.records[3].rgb_path.write_bytes(b"not an image")
    cv2.imwrite(str(seq.records[5].depth_path), np.zeros((240, 320), np.uint8))  # 8-bit depth
    cv2.imwrite(str(seq.records[7].depth_path), np.zeros((100, 100), np.uint16))  # wrong size
    with pytest.raises(DatasetError, match=str(seq.records[3].rgb_path)):
        seq.read(3)
    with pytest.raises(DatasetError, match="16-bit"):
        seq.read(5)
    with pytest.raises(DatasetError, match="differs from colour size"):
        seq.read(7)
    frames = list(seq.frames(0, 10))
    assert [f.index for f in frames] == [0, 1, 2, 4, 6, 8, 9]
    assert seq.skipped == [3, 5, 7]


def test_undistortion_moves_pixels_to_the_pinhole_projection():
    from twohr.dataset import CameraIntrinsics, undistorted

    pinhole = CAMERA_PRESETS["tum_fr3"]
    image = np.zeros((480, 640), np.uint8)
    assert undistorted(image, pinhole) is image  # no distortion: nothing to do, no copy
    camera = CAMERA_PRESETS["tum_fr1"]
    assert camera.distorted and isinstance(camera, CameraIntrinsics)
    point = np.array([[0.45, -0.3, 1.0]])  # towards a corner, where the lens bends most
    seen, _ = cv2.projectPoints(point, np.zeros(3), np.zeros(3), camera.matrix, np.array(camera.distortion))
    u, v = np.round(seen.reshape(2)).astype(int)
    image[v - 1:v + 2, u - 1:u + 2] = 255
    depth = np.zeros((480, 640), np.uint16)
    depth[v - 1:v + 2, u - 1:u + 2] = 5000
    fixed, fixed_depth = undistorted(image, camera), undistorted(depth, camera, depth=True)
    ys, xs = np.nonzero(fixed > 64)
    pinhole_uv = (camera.matrix @ point[0])[:2]
    shift = np.hypot(u - pinhole_uv[0], v - pinhole_uv[1])
    assert shift > 5  # the lens moved this point by several pixels
    assert np.hypot(xs.mean() - pinhole_uv[0], ys.mean() - pinhole_uv[1]) < 1.0 + np.hypot(*(seen.reshape(2) - (u, v)))
    assert set(np.unique(fixed_depth)) == {0, 5000}  # nearest: no depth blended between 0 and 5 m
