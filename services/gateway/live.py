"""The gateway's live view: every robot's frames, keypoints, masks, poses and map points from the bus, shown on
a Foxglove WebSocket server (:class:`twohr.foxglove_live.LiveView`).

Samples go through a small drop-oldest queue to one worker thread: a slow viewer loses old frames, it never
holds up the bus.
"""

from __future__ import annotations

import collections
import logging
import threading

import zenoh

from twohr import keys
from twohr.foxglove_live import LiveView
from twohr.messages import ControlMsg, MessageError, decode

log = logging.getLogger("twohr.gateway.live")

STREAMS = ("frames", "keypoints", "dynamics", "pose", "landmarks", "path")


class BusLiveView:
    """A :class:`LiveView` on ``host:port`` fed by a Zenoh session's subscriptions."""

    def __init__(self, session: zenoh.Session, host: str, port: int, backlog: int = 32) -> None:
        self.view = LiveView(host, port)
        self.queue: collections.deque = collections.deque(maxlen=backlog)
        self.ready = threading.Condition()
        self.malformed = 0
        self.stopping = False
        self.subscribers = [session.declare_subscriber(keys.all_robots(stream), self._on_sample)
                            for stream in (*STREAMS, keys.CONTROL)]
        self.thread = threading.Thread(target=self._run, name="live-view", daemon=True)
        self.thread.start()

    def _on_sample(self, sample) -> None:
        with self.ready:
            self.queue.append((str(sample.key_expr), sample.payload.to_bytes()))
            self.ready.notify()

    def _run(self) -> None:
        while True:
            with self.ready:
                while not self.queue and not self.stopping:
                    self.ready.wait(0.5)
                if self.stopping:
                    return
                key, payload = self.queue.popleft()
            try:
                if keys.parse(key)[1] == keys.CONTROL:
                    control, _ = decode(payload, ControlMsg)
                    if control.command == "start":  # every channel up front: none loses its first message
                        self.view.reset(control.robot_id)
                        self.view.advertise(control.robot_id)
                else:
                    self.view.convert_and_log(payload)
            except (MessageError, ValueError) as exc:
                self.malformed += 1
                log.debug("live view skipped %s: %s", key, exc)

    def close(self) -> None:
        for subscriber in self.subscribers:
            subscriber.undeclare()
        with self.ready:
            self.stopping = True
            self.ready.notify()
        self.thread.join(timeout=2)
        self.view.close()
