"""The backwards variant of a sequence: the same frames in reverse order, timestamps mirrored."""

from __future__ import annotations

import numpy as np

from twohr.dataset import RGBDSequence
from twohr_lab.tracking.backwards import backwards


def test_a_backwards_sequence_plays_the_frames_in_reverse_with_mirrored_times(synthetic_sequence, tmp_path):
    forward = RGBDSequence(synthetic_sequence)
    variant = RGBDSequence(backwards(synthetic_sequence, tmp_path))
    assert variant.root.name == f"{synthetic_sequence.name}_backwards" and len(variant) == len(forward)
    n = len(forward)
    for index in (0, 7, n - 1):
        assert np.array_equal(variant.read(index).rgb, forward.read(n - 1 - index).rgb)
        assert np.array_equal(variant.read(index).depth, forward.read(n - 1 - index).depth)
    t, s = forward.stamps, variant.stamps
    assert np.all(np.diff(s) > 0) and s[0] == t[0] and s[-1] == t[-1]
    assert np.allclose(s, (t[0] + t[-1]) - t[::-1], atol=1e-4)
    gt_forward, gt_variant = forward.ground_truth(), variant.ground_truth()
    assert np.allclose(gt_variant.poses, gt_forward.poses[::-1], atol=1e-5)
    assert np.all(np.diff(gt_variant.stamps) > 0)


def test_a_repeated_sequence_plays_the_frames_again_later(synthetic_sequence, tmp_path):
    from twohr_lab.tracking.backwards import repeated

    once = RGBDSequence(synthetic_sequence)
    thrice = RGBDSequence(repeated(synthetic_sequence, tmp_path, 3))
    n = len(once)
    assert thrice.root.name == f"{synthetic_sequence.name}_x3" and len(thrice) == 3 * n
    assert np.array_equal(thrice.read(n + 5).rgb, once.read(5).rgb)
    assert np.array_equal(thrice.read(2 * n + 9).depth, once.read(9).depth)
    assert np.all(np.diff(thrice.stamps) > 0)  # each pass after the one before, one frame spacing apart
    assert np.isclose(thrice.stamps[n] - thrice.stamps[n - 1], np.median(np.diff(once.stamps)), atol=1e-4)
    gt = thrice.ground_truth()
    assert len(gt) == 3 * len(once.ground_truth()) and np.allclose(gt.poses[len(gt) // 3], gt.poses[0])
