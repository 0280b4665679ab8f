"""Frames decoded once, before any clock starts: how ``twohr bench`` times ours like ORB-SLAM3's examples time
theirs, and whether the machine's memory holds them."""

from __future__ import annotations

from pathlib import Path


def memory_available_mib() -> float | None:
    """Memory available to a new allocation without swapping (Linux ``MemAvailable``), MiB; None elsewhere."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) / 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def frames_fit_in_memory(sequence, start: int, stop: int, share: float = 0.5) -> tuple[bool, str]:
    """Whether holding frames ``start:stop`` decoded takes at most ``share`` of the memory available, and why not."""
    first = next(iter(sequence.frames(start, stop)), None)
    if first is None:
        return False, "no readable frame"
    need = (first.rgb.nbytes + first.depth.nbytes) * (stop - start) / 2**20
    available = memory_available_mib()
    if available is not None and need > share * available:
        return False, (f"holding {stop - start} decoded frames takes {need:.0f} MiB, over {share:.0%} of the "
                       f"{available:.0f} MiB available: bench fewer --frames to time like for like")
    return True, ""


class FramesInMemory:
    """A sequence whose frames ``start:stop`` were read and decoded once, before any clock started. ORB-SLAM3's
    examples time tracking on frames already in memory; the like-for-like ratio times ours the same way. Each pass
    hands out fresh :class:`~twohr.dataset.Frame` objects over the same arrays, so nothing cached by one run (the
    grey image) helps the next."""

    def __init__(self, sequence, start: int, stop: int) -> None:
        self._sequence = sequence
        self._arrays = {f.index: (f.stamp, f.rgb, f.depth) for f in sequence.frames(start, stop)}

    def frames(self, start: int = 0, stop: int | None = None, step: int = 1):
        """Frames in order, as :meth:`RGBDSequence.frames` (skipped frames stay skipped)."""
        from twohr.dataset import Frame

        for index in range(start, len(self) if stop is None else min(stop, len(self)), step):
            if index in self._arrays:
                stamp, rgb, depth = self._arrays[index]
                yield Frame(index, stamp, rgb, depth)

    def __len__(self) -> int:
        return len(self._sequence)

    def __getattr__(self, name: str):
        return getattr(self._sequence, name)
