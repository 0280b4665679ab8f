"""Well-known paths and the safe resolution of user-supplied paths against configured roots."""

from __future__ import annotations

import os
from pathlib import Path

from .errors import TwohrError

#: The development sequence (the first 560 frames of Bonn ``rgbd_bonn_crowd``), relative to the repository root:
#: the default ``--sequence`` of the commands and studies. The data lives in ``../shared`` beside the repository.
DEV_SEQUENCE = "../shared/data/rgbd_bonn_crowd_dev"


def resolve_under_roots(path: str, roots: list[Path]) -> Path:
    """The real path of ``path`` if it lies inside one of ``roots``; otherwise a :class:`TwohrError`.

    Relative paths are taken relative to each root in turn. ``..`` is refused outright, and symlinks
    are resolved before the check, so nothing outside the roots can be reached."""
    if not path or "\x00" in path:
        raise TwohrError("empty or invalid path")
    if ".." in Path(path).parts:
        raise TwohrError(f"'..' is not allowed in a sequence path: {path}")
    candidates = [Path(path)] if Path(path).is_absolute() else [root / path for root in roots]
    for candidate in candidates:
        real = candidate.resolve()
        for root in roots:
            if real == root.resolve() or root.resolve() in real.parents:
                if not real.is_dir():
                    raise TwohrError(f"sequence folder not found: {path}")
                return real
    raise TwohrError(f"{path} is not under the data roots {[str(r) for r in roots]}")


def open_private(path: str | Path, mode: str = "wb"):
    """``open(path, mode)`` for writing a new (or emptied) file that only its owner may read: 0600 from its creation,
    whatever the umask, and a file already there is narrowed to it (recordings show the robots' surroundings)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o600)
    try:
        os.fchmod(fd, 0o600)
        return os.fdopen(fd, mode)
    except BaseException:
        os.close(fd)
        raise
