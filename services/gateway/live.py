"""The gateway's live view: every robot's frames, keypoints, masks, poses and map points from the bus, shown on
a Foxglove WebSocket server (:class:`twohr.foxglove_live.LiveView`).

Samples go through a small drop-oldest queue to one worker thread, and each viewer has its own drop-oldest queue
in the server: a slow viewer loses old frames, it never holds up the bus or the other viewers.

On a fleet's keys (``--tls-keys``) the live view is as guarded as the HTTP API (:func:`live_access`): TLS with the
gateway's certificate, and a token in the URL (``?token=``) checked before the WebSocket upgrade. The operator's
token sees every robot; a robot's token (the tokens file, read again when it changes, as the HTTP API reads it)
sees its own channels and the others' poses, paths and transforms.
"""

from __future__ import annotations

import collections
import logging
import secrets
import ssl
import threading

import zenoh

from twohr import keys
from twohr.foxglove_live import EVERYTHING, Authorize, LiveView, Viewer, robot_viewer, server_tls
from twohr.identity import CERT_FILE, KEY_FILE
from twohr.messages import ControlMsg, MessageError, decode

from .tokens import RobotTokens

log = logging.getLogger("twohr.gateway.live")

STREAMS = ("frames", "keypoints", "dynamics", "pose", "landmarks", "path")


def live_access(settings) -> tuple[ssl.SSLContext | None, Authorize | None]:
    """The live view's TLS and token check for the gateway's ``settings`` (a ``GatewaySettings``): none without
    ``tls_keys``; with them TLS, and the operator's token (``api_token``) or a robot's (``robot_tokens``)."""
    if settings.tls_keys is None:
        return None, None
    robots = RobotTokens(settings.robot_tokens) if settings.robot_tokens else None

    def authorize(token: str) -> Viewer | None:
        operator = settings.api_token
        # compared as bytes: a token with non-ASCII characters is simply a wrong one
        if operator and secrets.compare_digest(token.encode("utf-8", "surrogateescape"), operator.encode()):
            return EVERYTHING
        robot = robots.robot_of(token) if robots is not None else None
        return robot_viewer(robot) if robot else None

    return server_tls(settings.tls_keys / CERT_FILE, settings.tls_keys / KEY_FILE), authorize


class BusLiveView:
    """A :class:`LiveView` on ``host:port`` fed by a Zenoh session's subscriptions; ``tls`` and ``authorize`` as
    :func:`live_access` makes them (None: plain WebSocket, no token)."""

    def __init__(self, session: zenoh.Session, host: str, port: int, backlog: int = 32,
                 tls: ssl.SSLContext | None = None, authorize: Authorize | None = None) -> None:
        self.view = LiveView(host, port, tls=tls, authorize=authorize)
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
