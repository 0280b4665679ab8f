"""The like-for-like timing of ``twohr bench``: frames decoded before the clock, as ORB-SLAM3 is timed."""

from __future__ import annotations

import numpy as np

from twohr.config import load_config
from twohr.dataset import RGBDSequence
from twohr_app.pipeline import run_sequence
from twohr_lab.bench.steps.frames import FramesInMemory, frames_fit_in_memory, memory_available_mib


def test_frames_held_in_memory_are_the_sequences_own_handed_out_afresh(synthetic_sequence):
    sequence = RGBDSequence(synthetic_sequence)
    held = FramesInMemory(sequence, 3, 12)
    first = list(held.frames(3, 12))
    assert [f.index for f in first] == list(range(3, 12))
    assert [f.index for f in held.frames(3, 12, 2)] == [3, 5, 7, 9, 11]
    assert list(held.frames(12, 20)) == []  # never read, so never handed out
    for frame in first:
        disk = sequence.read(frame.index)
        assert frame.stamp == disk.stamp
        assert np.array_equal(frame.rgb, disk.rgb) and np.array_equal(frame.depth, disk.depth)
    again = next(held.frames(3, 4))
    assert again is not first[0] and again.rgb is first[0].rgb  # a fresh frame over the same decoded arrays
    assert len(held) == len(sequence) and held.camera == sequence.camera and held.name == sequence.name

    run = run_sequence(held, load_config(preset="orb"), start=3, stop=12, progress=False)
    assert [s.index for s in run.stats] == list(range(3, 12))
    assert run.tracked_percent > 80


def test_frames_are_held_only_where_they_fit_in_the_memory_available(synthetic_sequence):
    sequence = RGBDSequence(synthetic_sequence)
    frame = sequence.read(0)
    need_mib = (frame.rgb.nbytes + frame.depth.nbytes) * 10 / 2**20
    available = memory_available_mib()
    assert available is not None and available > need_mib  # Linux, and ten small frames fit
    assert frames_fit_in_memory(sequence, 0, 10) == (True, "")
    fits, why = frames_fit_in_memory(sequence, 0, 10, share=need_mib / available / 2)
    assert not fits and "bench fewer --frames" in why and f"{need_mib:.0f} MiB" in why
