"""Replicas of a network service (detector, yolo, matcher) and how one caller spreads its jobs over them.

Each service process is a replica: it holds the liveliness token ``twohr/_alive/<service>/<replica>`` and answers
``twohr/<robot>/<query>/<replica>`` (:meth:`twohr.service.Service.declare_replica_queryable`). A caller (the
tracker) follows the tokens and sends each job to exactly one replica, the least busy: the one with the fewest of
its jobs in flight, ties going to the one that has served the fewest. A job whose replica goes away before it
answers (the process killed, its host gone: no reply, or none in time) is sent again to another replica; a job a
replica *answered* with an error is not, since another replica would answer the same. Replicas may live on any
host joined to the router mesh; one that comes back rejoins by its token alone.
"""

from __future__ import annotations

import collections
import threading
import time

import zenoh

from . import keys
from .messages import MessageError


class NoReplica(TimeoutError):
    """No replica of a service answered a job: none alive, or every one tried went away or timed out."""


class Replicas:
    """The live replicas of one service as one caller sees them, and its jobs' dispatch across them."""

    def __init__(self, session: zenoh.Session, service: str, wait_for_one: float = 10.0) -> None:
        self.session, self.service, self.wait_for_one = session, service, wait_for_one
        self._lock = threading.Condition()
        self._alive: set[str] = set()
        self._in_flight: collections.Counter[str] = collections.Counter()
        self.answered: collections.Counter[str] = collections.Counter()  # jobs each replica answered
        self.retried = 0  # jobs sent again after their replica went away
        self.lost = 0  # jobs no replica answered
        self.bytes_sent = 0  # the jobs' payloads, each time one was sent
        self.bytes_received = 0  # the answers'
        self._subscriber = session.liveliness().declare_subscriber(keys.alive_key(service), self._on_token,
                                                                    history=True)

    def _on_token(self, sample: zenoh.Sample) -> None:
        try:
            _, replica = keys.parse_replica_key(str(sample.key_expr))
        except ValueError:
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive.add(replica)
                self._lock.notify_all()
            else:
                self._alive.discard(replica)

    def alive(self) -> list[str]:
        with self._lock:
            return sorted(self._alive)

    def pick(self, exclude: set[str] = frozenset(), wait: float = 0.0) -> str | None:
        """The least busy live replica not in ``exclude`` (waiting up to ``wait`` s for one to appear), or None."""
        deadline = time.monotonic() + wait
        with self._lock:
            while not (candidates := self._alive - exclude):
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._lock.wait(left)
            return min(candidates, key=lambda r: (self._in_flight[r], self.answered[r], r))

    def call(self, robot_id: str, query: str, payload: bytes, timeout: float = 10.0) -> bytes:
        """Send one job to one replica and return its answer's bytes; sent again to another replica if the first
        goes away without answering. :class:`MessageError` for an error answer, :class:`NoReplica` when none
        answers."""
        tried: set[str] = set()
        while (replica := self.pick(tried, wait=self.wait_for_one if not tried else 0.0)) is not None:
            with self._lock:
                self._in_flight[replica] += 1
                self.bytes_sent += len(payload)
            try:
                reply = next(iter(self.session.get(keys.replica_query(robot_id, query, replica), payload=payload,
                                                   timeout=timeout)), None)
            finally:
                with self._lock:
                    self._in_flight[replica] -= 1
            if reply is not None and reply.ok is not None:
                answer = reply.ok.payload.to_bytes()
                with self._lock:
                    self.answered[replica] += 1
                    self.bytes_received += len(answer)
                return answer
            if reply is not None:
                raise MessageError(f"{self.service} {replica}: {reply.err.payload.to_bytes().decode(errors='replace')}")
            tried.add(replica)
            with self._lock:
                self.retried += 1
        with self._lock:
            self.lost += 1
        raise NoReplica(f"no {self.service} replica answered {keys.key(robot_id, query)}"
                        + (f" (tried {', '.join(sorted(tried))})" if tried else f" within {self.wait_for_one:.0f} s"))

    def stats(self) -> dict:
        """What :meth:`call` did: jobs answered per replica, jobs sent again, jobs lost, and the live replicas."""
        with self._lock:
            return {"alive": sorted(self._alive), "answered": dict(self.answered), "retried": self.retried,
                    "lost": self.lost, "bytes_sent": self.bytes_sent, "bytes_received": self.bytes_received}

    def close(self) -> None:
        self._subscriber.undeclare()
