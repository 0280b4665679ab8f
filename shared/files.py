"""Files replaced whole: a reader finds the old file or the whole new one, never a part.

The new content goes to a temporary file beside the target (``mkstemp``: ``O_EXCL``, created 0600, so a private file
is never readable by others, not even for an instant), written through the descriptor that created it, which then
takes the target's place in one rename. The folder is made when missing; ``durable`` adds the fsyncs that make the
new file and the rename survive a power cut."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

#: ``mode`` for a file anyone may read as usual: what ``open`` makes (0666 less the umask)
AS_OPEN = None


def umask() -> int:
    """This process's umask, read without changing it (another thread may be creating a file)."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    current = os.umask(0o022)  # no /proc: the only other way to read it is to set it
    os.umask(current)
    return current


@contextlib.contextmanager
def replacing(path: str | Path, mode: int | None = 0o600, durable: bool = False, folder_mode: int = 0o777,
              suffix: str = ".tmp") -> Iterator[BinaryIO]:
    """The new file for ``path``, open for binary writing; when the block ends without an error it replaces
    ``path``, otherwise it is removed and ``path`` stays as it was. A tool that writes by name writes to its
    ``name`` (a temporary path beside ``path``, ending in ``suffix``: some tools add an extension a name lacks).

    ``mode``: the new file's permissions (0600 by default: private; :data:`AS_OPEN` for what ``open`` would give
    it). ``folder_mode``: of the folders made for it (less the umask)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True, mode=folder_mode)
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    try:
        with os.fdopen(handle, "wb") as out:
            out.raw.name = temporary  # as open() names a file: a tool that writes by name reads it there
            wanted = 0o666 & ~umask() if mode is AS_OPEN else mode
            if wanted != 0o600:
                os.fchmod(out.fileno(), wanted)
            yield out
            out.flush()
            if durable:
                os.fsync(out.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    if durable:
        folder = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(folder)  # the rename itself
        finally:
            os.close(folder)


def write_atomic(path: str | Path, data: bytes | str, mode: int | None = 0o600, durable: bool = False,
                 folder_mode: int = 0o777) -> Path:
    """Replace ``path`` with ``data`` (text as UTF-8) as :func:`replacing` does; returns ``path``."""
    with replacing(path, mode, durable, folder_mode) as out:
        out.write(data.encode() if isinstance(data, str) else data)
    return Path(path)
