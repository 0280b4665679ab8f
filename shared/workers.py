"""Small concurrency helpers for the camera-rate pipeline: a one-job background worker and a frame prefetcher.

ONNX Runtime, OpenVINO and OpenCV release the GIL while they compute, so one worker thread per
heavy stage runs on the other core while the per-frame path goes on.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Iterable, Iterator
from typing import Generic, TypeVar

Job = TypeVar("Job")
Result = TypeVar("Result")
Item = TypeVar("Item")


class Worker(Generic[Job, Result]):
    """Runs ``fn(job)`` on one background thread, one job at a time; callers never wait for it.

    :meth:`submit` hands over a job only when the worker is idle (the caller decides which frame is
    worth the work, so the freshest one wins); :meth:`poll` returns the finished result, if any.
    With ``synchronous=True`` the job runs inside :meth:`submit`, which makes runs deterministic (tests).
    An exception in ``fn`` is re-raised by the next :meth:`poll` or :meth:`wait`.
    """

    def __init__(self, fn: Callable[[Job], Result], name: str, synchronous: bool = False) -> None:
        self.fn = fn
        self.name = name
        self.synchronous = synchronous
        self._done: Result | None = None
        self._error: BaseException | None = None
        self._busy = False
        self._lock = threading.Lock()
        self._jobs: queue.Queue = queue.Queue(maxsize=1)
        self._idle = threading.Event()
        self._idle.set()
        self._thread: threading.Thread | None = None
        if not synchronous:
            self._thread = threading.Thread(target=self._loop, name=f"twohr-{name}", daemon=True)
            self._thread.start()

    @property
    def busy(self) -> bool:
        """True while a job is running or its result has not been collected."""
        with self._lock:
            return self._busy

    def submit(self, job: Job) -> bool:
        """Start ``job`` if the worker is idle; returns False (and drops the job) when it is busy."""
        with self._lock:
            if self._busy:
                return False
            self._busy = True
        self._idle.clear()
        if self.synchronous:
            self._run(job)
        else:
            self._jobs.put(job)
        return True

    def poll(self) -> Result | None:
        """The finished job's result (once), or None while it runs or when there was none."""
        with self._lock:
            if self._error is not None:
                error, self._error, self._busy = self._error, None, False
                raise error
            if not self._idle.is_set():
                return None
            result, self._done, self._busy = self._done, None, False
            return result

    def wait(self, timeout: float | None = None) -> Result | None:
        """Block until the running job is finished, then :meth:`poll`."""
        self._idle.wait(timeout)
        return self.poll()

    def close(self) -> None:
        """Stop the thread after the running job."""
        if self._thread is not None:
            self._jobs.put(None)
            self._thread.join()
            self._thread = None

    def _run(self, job: Job) -> None:
        try:
            result = self.fn(job)
            with self._lock:
                self._done = result
        except BaseException as exc:  # handed to the caller by poll()
            with self._lock:
                self._error = exc
        finally:
            self._idle.set()

    def _loop(self) -> None:
        while (job := self._jobs.get()) is not None:
            self._run(job)


_END = object()


def prefetch(items: Iterable[Item], depth: int = 4) -> Iterator[Item]:
    """Iterate ``items`` produced on a background thread, up to ``depth`` ahead (image decoding overlaps
    the consumer's work). Exceptions in the producer are re-raised in the consumer."""
    buffer: queue.Queue = queue.Queue(maxsize=max(1, depth))
    stop = threading.Event()

    def produce() -> None:
        try:
            for item in items:
                if stop.is_set():
                    return
                buffer.put(item)
            buffer.put(_END)
        except BaseException as exc:
            buffer.put(exc)

    thread = threading.Thread(target=produce, name="twohr-prefetch", daemon=True)
    thread.start()
    try:
        while (item := buffer.get()) is not _END:
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        while thread.is_alive():  # unblock a producer waiting on a full buffer
            try:
                buffer.get(timeout=0.05)
            except queue.Empty:
                pass
