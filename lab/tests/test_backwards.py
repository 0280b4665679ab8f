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
