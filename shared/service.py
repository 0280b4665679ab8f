"""The thin shell every service shares: subscribe, queue, call the core, publish.

A :class:`Service` subscribes to key expressions, puts each sample into a bounded
:class:`Inbox` (policy ``drop_oldest`` or ``backpressure``), and one worker thread hands the
samples to :meth:`Service.handle`. A malformed payload is counted and logged, never fatal.
Each service answers a health query on ``twohr/_health/<name>`` with its counters.
"""

from __future__ import annotations

import collections
import json
import logging
import os
import signal
import threading
import time
from dataclasses import dataclass, field
from typing import Literal

import zenoh

from . import keys
from .bus import HEALTH_PREFIX, BusConfig, open_session
from .config import PipelineConfig
from .messages import ControlMsg, FrameMsg, MessageError, decode

QueuePolicy = Literal["drop_oldest", "backpressure"]


@dataclass
class Counters:
    """What a service has seen; read by the health query and the tests."""

    received: int = 0
    processed: int = 0
    dropped: int = 0
    malformed: int = 0
    errors: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def add(self, name: str, n: int = 1) -> None:
        with self.lock:
            setattr(self, name, getattr(self, name) + n)

    def as_dict(self) -> dict[str, int]:
        with self.lock:
            return {k: getattr(self, k) for k in ("received", "processed", "dropped", "malformed", "errors")}


class Inbox:
    """A bounded FIFO. ``drop_oldest`` discards the oldest item when full (fresh data wins, for live
    cameras); ``backpressure`` blocks the producer until there is room (nothing lost, for playback)."""

    def __init__(self, maxsize: int, policy: QueuePolicy, counters: Counters) -> None:
        self.items: collections.deque = collections.deque()
        self.urgent: collections.deque = collections.deque()  # control messages and queries
        self.maxsize = maxsize
        self.policy = policy
        self.counters = counters
        self.cond = threading.Condition()

    def put(self, item, urgent: bool = False) -> None:
        """Queue ``item``; ``urgent`` items (control messages, queries) are never dropped and go first."""
        with self.cond:
            if urgent:
                self.urgent.append(item)
            elif self.policy == "backpressure":
                while len(self.items) >= self.maxsize:
                    self.cond.wait(0.1)
            elif len(self.items) >= self.maxsize:
                self.items.popleft()
                self.counters.add("dropped")
            if not urgent:
                self.items.append(item)
            self.cond.notify_all()

    def get(self, timeout: float):
        with self.cond:
            if not self.items and not self.urgent:
                self.cond.wait(timeout)
            if self.urgent:
                return self.urgent.popleft()
            if not self.items:
                return None
            item = self.items.popleft()
            self.cond.notify_all()
            return item

    def __len__(self) -> int:
        return len(self.items) + len(self.urgent)


class Service:
    """Base class of the service adapters. Subclasses set ``name``, list ``subscriptions()`` and
    implement ``handle(key, payload)``; they publish with ``self.publish(key, payload)``."""

    name = "service"
    #: subscribe to control messages and keep ``session_configs`` (the pipeline stages do)
    follows_sessions = False

    def __init__(self, bus: BusConfig | None = None, queue_size: int = 8, policy: QueuePolicy = "backpressure") -> None:
        self.bus = bus or BusConfig()
        self.counters = Counters()
        self.inbox = Inbox(queue_size, policy, self.counters)
        self.log = logging.getLogger(f"twohr.{self.name}")
        self.session: zenoh.Session | None = None
        self.stopping = threading.Event()
        self._publishers: dict[str, zenoh.Publisher] = {}
        self.session_configs: dict[str, PipelineConfig] = {}

    # -- to override
    def subscriptions(self) -> list[str]:
        return []

    def on_session_start(self, control: ControlMsg) -> None:
        """A session starts: set up per-session state (its config is ``control.config``)."""

    def on_session_stop(self, session_id: str) -> None:
        """A session ends: drop its per-session state."""

    def handle(self, key: str, payload: bytes) -> None:
        raise NotImplementedError

    def on_start(self) -> None:
        """Called once the bus session is open (declare queryables here)."""

    def health(self) -> dict:
        return {"service": self.name, "queue": len(self.inbox), **self.counters.as_dict()}

    # -- the shell
    def publish(self, key: str, payload: bytes) -> None:
        if key not in self._publishers:
            self._publishers[key] = declare_publisher(self.session, key)
        self._publishers[key].put(payload)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        self.counters.add("received")
        key = str(sample.key_expr)
        self.inbox.put((key, sample.payload.to_bytes()), urgent=key.endswith("/" + keys.CONTROL))

    def _on_query(self, query: zenoh.Query) -> None:
        """Queue a query (a request/reply stage); it is served before any queued stream sample."""
        self.counters.add("received")
        self.inbox.put((str(query.key_expr), query), urgent=True)

    def config_for(self, session_id: str) -> PipelineConfig:
        """The pipeline config of a session (the defaults if its start was never seen)."""
        if session_id not in self.session_configs:
            self.log.warning("no start message seen for session %s: using the default config", session_id)
            self.session_configs[session_id] = PipelineConfig()
        return self.session_configs[session_id]

    def streams_frame(self, payload: bytes) -> bool:
        """Whether a streamed frame is this stage's to process: not in a ``keyframes`` session, where the
        tracker asks the detector and yolo stages by query for the frames it needs."""
        header, _ = decode(payload, FrameMsg, only=())
        return self.config_for(header.session_id).pipeline.mode != "keyframes"

    def _handle_control(self, payload: bytes) -> None:
        control, _ = decode(payload, ControlMsg)
        if control.command == "start":
            self.session_configs[control.session_id] = control.config
            self.on_session_start(control)
        else:
            self.on_session_stop(control.session_id)
            self.session_configs.pop(control.session_id, None)

    def _on_health(self, query: zenoh.Query) -> None:
        query.reply(query.key_expr, json.dumps(self.health()))

    def process_one(self, timeout: float = 0.2) -> bool:
        """Handle one queued sample; False if none arrived within ``timeout``."""
        item = self.inbox.get(timeout)
        if item is None:
            return False
        key, payload = item
        try:
            if self.follows_sessions and key.endswith("/" + keys.CONTROL):
                self._handle_control(payload)
            else:
                self.handle(key, payload)
            self.counters.add("processed")
        except MessageError as exc:
            self.counters.add("malformed")
            self.log.warning("dropped malformed message on %s: %s", key, exc)
        except Exception:  # a bad frame must not take the service down
            self.counters.add("errors")
            self.log.exception("error while handling %s", key)
        return True

    def run(self, stop: threading.Event | None = None) -> None:
        """Serve until ``stop`` is set (or SIGINT/SIGTERM when run as a program)."""
        stop = stop or self.stopping
        self.session = open_session(self.bus)
        wanted = self.subscriptions() + ([keys.all_robots(keys.CONTROL)] if self.follows_sessions else [])
        subscribers = [self.session.declare_subscriber(k, self._on_sample) for k in wanted]
        queryable = self.session.declare_queryable(f"{HEALTH_PREFIX}/{self.name}", self._on_health)
        self.on_start()
        self.log.info("%s serving %s", self.name, ", ".join(self.subscriptions()) or "(no subscriptions)")
        try:
            while not stop.is_set():
                self.process_one()
        finally:
            for sub in subscribers:
                sub.undeclare()
            queryable.undeclare()
            self.session.close()

    def run_forever(self) -> None:
        """Entry point for ``python -m``: stop cleanly on SIGINT and SIGTERM."""
        logging.basicConfig(level=os.environ.get("TWOHR_LOG_LEVEL", "INFO"),
                            format="%(asctime)s %(levelname)s %(name)s: %(message)s")
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: self.stopping.set())
        self.run(self.stopping)


def reply_to(query: zenoh.Query, answer) -> None:
    """Answer a query with ``answer(payload) -> bytes``; anything that goes wrong is replied as an error at
    once (the caller must not wait out its timeout) and then raised for the service's counters."""
    payload = query.payload.to_bytes() if query.payload is not None else b""
    try:
        data = answer(payload)
    except Exception as exc:
        query.reply_err(f"{type(exc).__name__}: {exc}"[:500].encode())
        raise
    query.reply(query.key_expr, data)


def declare_publisher(session: zenoh.Session, key: str, wait_for_subscribers: float = 2.0) -> zenoh.Publisher:
    """A reliable, blocking publisher; waits up to ``wait_for_subscribers`` s until the bus reports a matching
    subscriber, so that the first messages on a new key are not dropped while routes are still being set up."""
    publisher = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
    deadline = time.monotonic() + wait_for_subscribers
    while not publisher.matching_status.matching and time.monotonic() < deadline:
        time.sleep(0.02)
    return publisher


def serve(service_cls: type[Service], argv: list[str] | None = None, **kwargs) -> None:
    """``python -m twohr_services.<name>``: parse ``--router`` and run the service until SIGINT/SIGTERM."""
    import argparse

    parser = argparse.ArgumentParser(prog=f"python -m twohr_services.{service_cls.name}",
                                     description=(service_cls.__doc__ or "").strip())
    parser.add_argument("--router", default=None, help="Zenoh router endpoint (default $TWOHR_ZENOH_ROUTER)")
    args = parser.parse_args(argv)
    bus = BusConfig(connect=[args.router]) if args.router else BusConfig()
    service_cls(bus, **kwargs).run_forever()
