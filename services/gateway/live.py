"""The gateway's live view: every robot's frames, keypoints, masks, poses and map points from the bus, shown on
a Foxglove WebSocket server (:class:`twohr.foxglove_live.LiveView`).

Samples go through a small drop-oldest queue to one worker thread, and each viewer has its own drop-oldest queue
in the server: a slow viewer loses old frames, it never holds up the bus or the other viewers.

On a fleet's keys (``--tls-keys``) the live view is as guarded as the HTTP API (:func:`live_access`): TLS with the
gateway's certificate, and a token in the URL (``?token=``) checked before the WebSocket upgrade, by the HTTP API's
own check (:class:`~.tokens.Tokens`). The token is a view token (``GET /live`` with an API token gives it: it opens
the live view and nothing else, so it is what a Foxglove URL carries) or, for tools, an API token itself. The
operator's sees every robot; a robot's (the tokens file, read again when it changes) sees its own channels and the
others' poses, paths and transforms.
"""

from __future__ import annotations

import collections
import logging
import ssl
import threading

import zenoh

from twohr import keys
from twohr.foxglove_live import EVERYTHING, Authorize, LiveView, Viewer, robot_viewer, server_tls
from twohr.identity import CERT_FILE, KEY_FILE
from twohr.messages import ControlMsg, MessageError, decode
from twohr.service import check_robot

from .tokens import Tokens

log = logging.getLogger("twohr.gateway.live")

STREAMS = ("frames", "keypoints", "dynamics", "pose", "landmarks", "path")
#: sessions the live view remembers the robot of (a start past this forgets the oldest)
MAX_SESSIONS = 1024


def live_access(settings, tokens: Tokens | None = None) -> tuple[ssl.SSLContext | None, Authorize | None]:
    """The live view's TLS and token check for the gateway's ``settings`` (a ``GatewaySettings``): none without
    ``tls_keys``; with them TLS, and the check the HTTP API makes (``tokens``, by default one made of the settings'
    ``api_token`` and ``robot_tokens``), which also takes the view token of an API token."""
    if settings.tls_keys is None:
        return None, None
    check = tokens if tokens is not None else Tokens(settings.api_token, settings.robot_tokens)

    def authorize(token: str) -> Viewer | None:
        caller = check.identify_viewer(token)
        if caller is None:
            return None
        return EVERYTHING if caller.robot is None else robot_viewer(caller.robot)

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
        self.sessions: dict[str, str] = {}  # session -> robot, of the sessions started (their start controls)
        # and the shared maps' merges: a robot's submap frame hung under the map's (FoxgloveConverter.merge)
        self.subscribers = [session.declare_subscriber(key, self._on_sample) for key in (
            *(keys.all_robots(stream) for stream in (*STREAMS, keys.CONTROL)), keys.merged_key())]
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
                header = check_robot(key, payload)
                if keys.parse(key)[1] == keys.CONTROL:
                    control, _ = decode(payload, ControlMsg)
                    self._follow(control)
                    if control.command == "start":  # every channel up front: none loses its first message
                        self.view.reset(control.robot_id)
                        self.view.advertise(control.robot_id)
                else:
                    if header is not None and self.sessions.get(header.session_id) != header.robot_id:
                        raise MessageError(f"robot {header.robot_id!r} runs no session {header.session_id}")
                    self.view.convert_and_log(payload)
            except (MessageError, ValueError) as exc:
                self.malformed += 1
                log.debug("live view skipped %s: %s", key, exc)

    def _follow(self, control: ControlMsg) -> None:
        """The sessions running, by their start controls: a message is drawn only for the robot whose session it
        is (a session id is no secret; the key says which robot sent it), so no robot draws as another, and a robot
        that runs nothing makes no channels. An ended session is kept (its refined path comes after its stop)
        until :data:`MAX_SESSIONS` newer ones started."""
        if control.command in ("start", "move"):
            self.sessions[control.session_id] = control.robot_id
            while len(self.sessions) > MAX_SESSIONS:
                self.sessions.pop(next(iter(self.sessions)))

    def close(self) -> None:
        for subscriber in self.subscribers:
            subscriber.undeclare()
        with self.ready:
            self.stopping = True
            self.ready.notify()
        self.thread.join(timeout=2)
        self.view.close()
