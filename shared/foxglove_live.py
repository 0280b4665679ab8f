"""A Foxglove WebSocket server (the ws-protocol, on ``websockets``) for the live view of any number of robots.

Open it in Foxglove: ``https://app.foxglove.dev/?ds=foxglove-websocket&ds.url=ws://HOST:PORT``. Channels are
advertised as their first message arrives (or all of a robot's at once, :meth:`LiveView.advertise`); the
messages come from :class:`~.foxglove_convert.FoxgloveConverter` (the same as in recordings), sent as the
protobuf bytes of foxglove-sdk's schemas. The gateway feeds it from the bus, ``twohr run --view`` from the pipeline.

On a fleet's keys the server speaks TLS and asks each viewer for a token in its URL (``?token=``: browsers cannot
set headers on a WebSocket), checked before the upgrade: a request without a valid one gets HTTP 401 and sees no
channel. What a viewer sees is decided per connection (:class:`Viewer`): the operator everything, a robot its own
channels and the others' poses, paths and transforms (:func:`robot_viewer`). This process is the only listener:
no other port serves the channels. A token that stops being valid (a robot revoked) closes its connections.

Each viewer has its own bounded queue of messages to send: a slow viewer loses its oldest messages, it never holds
up the caller of :meth:`LiveView.log` or the other viewers. Both names of the subprotocol are accepted: the
spec's ``foxglove.websocket.v1`` (Lichtblick, older Foxglove Studio, the ws-protocol clients) and foxglove-sdk's
``foxglove.sdk.v1``.
"""

from __future__ import annotations

import asyncio
import base64
import collections
import contextlib
import json
import logging
import ssl
import struct
import threading
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from http import HTTPStatus
from pathlib import Path
from urllib.parse import parse_qs, quote, urlencode, urlsplit

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from websockets.asyncio.server import ServerConnection, serve
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from .errors import TwohrError
from .foxglove_convert import TF_TOPIC, TOPIC_TYPES, FoxgloveConverter, topics

log = logging.getLogger("twohr.live")
#: the server's own lines (websockets'): never below INFO, as its debug lines carry the request line, token included
_ws_log = logging.getLogger("twohr.live.websockets")
_ws_log.setLevel(logging.INFO)

#: the protocol's name in its spec first: a client that offers both gets it
SUBPROTOCOLS = ("foxglove.websocket.v1", "foxglove.sdk.v1")
#: what a robot sees of the other robots: what the bus already lets it read (poses, paths, transforms); never
#: their camera, keypoints, masks, calibration or map points
SHARED_KINDS = ("pose", "path", "keyframes", "path_refined", "tf")
MESSAGE_DATA = struct.Struct("<BIQ")  # opcode 0x01, subscription id, log time (ns); the payload follows
#: what one viewer may have waiting: past either bound its oldest messages are dropped
VIEWER_BACKLOG, VIEWER_BACKLOG_BYTES = 512, 16 << 20
#: viewers at once: without tokens, all of them; with tokens, the robots' together (each robot at most
#: VIEWERS_PER_ROBOT), and the operator's on their own, so that no robot can fill the server and keep the operator out
MAX_VIEWERS, VIEWERS_PER_ROBOT, OPERATOR_VIEWERS = 32, 4, 8
#: a subscription id is a u32 on the wire
MAX_SUBSCRIPTION_ID = 2**32 - 1
#: batches of messages logged and not yet handed to the viewers' queues: past it the oldest go (the server's loop is
#: behind the producer)
OUTBOX = 64
#: how often the tokens of open connections are checked again (a revoked robot's viewer is closed)
RECHECK_S = 1.0
CLIENT_MESSAGE_BYTES = 1 << 16  # viewers send only subscribe and unsubscribe
#: how long a viewer's TLS and WebSocket handshakes may take: on a small CPU busy with the stack, more than
#: websockets' default 10 s has been seen
OPEN_TIMEOUT_S = 30.0


@dataclass(frozen=True)
class Viewer:
    """Who is watching (a name for the log) and which topics it may see."""

    name: str
    sees: Callable[[str], bool] = field(repr=False)


def sees_as_robot(robot_id: str, topic: str) -> bool:
    """Whether robot ``robot_id`` may see ``topic``: its own channels, and the others' :data:`SHARED_KINDS`."""
    if topic == TF_TOPIC or topic.startswith(f"/{robot_id}/"):
        return True
    other = topic.split("/")[1] if topic.count("/") >= 2 else ""
    return bool(other) and topic in {topics(other)[kind] for kind in SHARED_KINDS}


def robot_viewer(robot_id: str) -> Viewer:
    """A robot's view: its own channels and the others' poses, paths and transforms."""
    return Viewer(f"robot {robot_id}", lambda topic: sees_as_robot(robot_id, topic))


#: the operator, or anyone where the live view needs no token
EVERYTHING = Viewer("operator", lambda topic: True)

#: token -> the viewer it admits, or None (refused); None as the view's ``authorize``: everyone sees everything
Authorize = Callable[[str], "Viewer | None"]


def server_tls(cert: Path, key: Path) -> ssl.SSLContext:
    """A TLS 1.3 server context with a certificate and its key (PEM); one line if they cannot be used."""
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.minimum_version = ssl.TLSVersion.TLSv1_3
    # no session tickets: a viewer does not resume sessions, and with the tickets sent after the handshake a
    # connection now and then stalled before its upgrade request was read (tests/test_live_view_security.py failed
    # 2 of 6 runs with them, none of 11 runs of it or its in-process tests without)
    context.num_tickets = 0
    try:
        context.load_cert_chain(cert, key)
    except (OSError, ssl.SSLError) as exc:
        raise TwohrError(f"live view: cannot use the certificate {cert} and key {key}: "
                         f"{getattr(exc, 'strerror', None) or exc}") from None
    return context


def view_url(host: str, port: int, tls: bool = False, token: str = "TOKEN") -> str:
    """The Foxglove app's address that opens this live view (on TLS, with ``token`` in the WebSocket's URL)."""
    if not tls:
        return f"https://app.foxglove.dev/?ds=foxglove-websocket&ds.url=ws://{host}:{port}"
    return f"https://app.foxglove.dev/?ds=foxglove-websocket&ds.url={quote(ws_url(host, port, token), safe='')}"


def ws_url(host: str, port: int, token: str = "TOKEN") -> str:
    """The WebSocket URL of a live view on TLS, with a token."""
    return f"wss://{host}:{port}/?{urlencode({'token': token})}"


@dataclass
class _Channel:
    id: int
    topic: str
    advert: dict  # as the advertise op names it


@dataclass(eq=False)
class _Client:
    """One viewer's connection: what it sees, its subscriptions and what waits to be sent to it."""

    connection: ServerConnection
    viewer: Viewer
    token: str | None
    subscriptions: dict[int, int] = field(default_factory=dict)  # channel id -> subscription id
    control: collections.deque = field(default_factory=collections.deque)  # JSON texts, sent before any data
    data: collections.deque = field(default_factory=collections.deque)  # (subscription, log time, payload)
    data_bytes: int = 0
    dropped: int = 0
    wake: asyncio.Event = field(default_factory=asyncio.Event)


class LiveView:
    """A Foxglove WebSocket server on ``host:port`` (port 0 picks a free one, see :attr:`port`).

    ``tls`` (:func:`server_tls`) serves ``wss://`` only; ``authorize`` (token -> :class:`Viewer` or None) makes the
    server ask every viewer for ``?token=`` before the upgrade. Without it anyone who reaches the port sees all."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, jpeg_quality: int | None = None,
                 path_every: int = 5, tls: ssl.SSLContext | None = None, authorize: Authorize | None = None) -> None:
        self.host, self.tls, self.authorize = host, tls, authorize
        self.converter = FoxgloveConverter(jpeg_quality, path_every)
        self.channels: dict[str, _Channel] = {}
        self.lock = threading.Lock()
        self.sent = 0
        self.clients: set[_Client] = set()
        self._subscribed: set[int] = set()  # channels someone subscribed to: only those are encoded
        self._outbox: collections.deque = collections.deque(maxlen=OUTBOX)  # batches for the loop to deliver
        self._delivering = False  # a delivery is scheduled on the loop
        self._outbox_lock = threading.Lock()  # not self.lock: the loop never waits on a conversion
        self._admitted: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # connection -> (viewer, token)
        self._session = str(time.time_ns())
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="foxglove-live", daemon=True)
        self.thread.start()
        try:
            self.server = asyncio.run_coroutine_threadsafe(self._start(host, port), self.loop).result(10)
        except OSError as exc:
            self._stop_loop()
            raise TwohrError(f"live view: cannot listen on {host}:{port}: {exc.strerror or exc}") from None
        self.port = self.server.sockets[0].getsockname()[1]
        self._recheck = asyncio.run_coroutine_threadsafe(self._recheck_tokens(), self.loop) if authorize else None

    async def _start(self, host: str, port: int):
        return await serve(self._serve, host, port, ssl=self.tls, subprotocols=list(SUBPROTOCOLS),
                           process_request=self._admit, compression=None, max_size=CLIENT_MESSAGE_BYTES,
                           logger=_ws_log, open_timeout=OPEN_TIMEOUT_S)

    @property
    def url(self) -> str:
        return view_url(self.host, self.port, self.tls is not None)

    # --- the producer's side (any thread) ---

    def _channel(self, topic: str, message_type: type, new: list[_Channel]) -> _Channel:
        channel = self.channels.get(topic)
        if channel is None:
            schema = message_type.get_schema()
            channel = self.channels[topic] = _Channel(len(self.channels) + 1, topic, {
                "id": len(self.channels) + 1, "topic": topic, "encoding": "protobuf", "schemaName": schema.name,
                "schema": base64.b64encode(schema.data).decode(), "schemaEncoding": schema.encoding})
            new.append(channel)
        return channel

    def advertise(self, robot_id: str) -> None:
        """Advertise a robot's channels now, so that a viewer can subscribe before its first frame."""
        new: list[_Channel] = []
        with self.lock:
            for kind, topic in topics(robot_id).items():
                self._channel(topic, TOPIC_TYPES[kind], new)
            if new:
                self.loop.call_soon_threadsafe(self._advertise, new)

    def log(self, messages: list[tuple[str, object]]) -> None:
        """Send ``(topic, Foxglove message)`` pairs, advertising each topic's channel on first use."""
        new: list[_Channel] = []
        batch = []
        with self.lock:
            now = time.time_ns()
            for topic, message in messages:
                channel = self._channel(topic, type(message), new)
                if channel.id in self._subscribed:  # a set read across threads: at worst one message is missed
                    batch.append((channel.id, now, message.encode()))
                self.sent += 1
            if new:
                self.loop.call_soon_threadsafe(self._advertise, new)
            if batch:  # no viewer gets a channel's message before its advertisement: it subscribes after that
                with self._outbox_lock:
                    self._outbox.append(batch)
                    scheduled, self._delivering = self._delivering, True
                if not scheduled:
                    self.loop.call_soon_threadsafe(self._deliver)

    def reset(self, robot_id: str) -> None:
        """A robot starts a new session: its path starts again."""
        with self.lock:
            self.converter.reset(robot_id)

    def convert_and_log(self, payload: bytes) -> None:
        """Show one bus message (raises ``MessageError`` if it is malformed)."""
        with self.lock:
            messages = self.converter.convert(payload)
        self.log(messages)

    # --- the server's side (its event loop) ---

    def _admit(self, connection: ServerConnection, request):
        """Before the upgrade: the token in the URL decides who this is, or the request gets 401 (503 when that
        viewer's share is full, see :data:`MAX_VIEWERS`)."""
        watching = [client.viewer for client in self.clients] + [viewer for viewer, _ in self._admitted.values()]
        if self.authorize is None:
            if len(watching) >= MAX_VIEWERS:
                return connection.respond(HTTPStatus.SERVICE_UNAVAILABLE, f"at most {MAX_VIEWERS} viewers\n")
            self._admitted[connection] = (EVERYTHING, None)
            return None
        token = (parse_qs(urlsplit(request.path).query).get("token") or [""])[0]
        try:
            viewer = self.authorize(token) if token else None
        except Exception:  # a check that fails lets no one in
            log.exception("live view: the token check failed")
            return connection.respond(HTTPStatus.SERVICE_UNAVAILABLE, "the token check failed: try again\n")
        if viewer is None:
            log.warning("live view: refused a viewer from %s: %s token", connection.remote_address[0],
                        "a wrong" if token else "no")
            return connection.respond(HTTPStatus.UNAUTHORIZED, "missing or wrong token: open the live view's URL "
                                      "with ?token=<a view token (GET /live with your API token gives it)>\n")
        full = _full(viewer, watching)
        if full:
            log.warning("live view: refused %s from %s: %s", viewer.name, connection.remote_address[0], full)
            return connection.respond(HTTPStatus.SERVICE_UNAVAILABLE, full + "\n")
        self._admitted[connection] = (viewer, token)
        return None

    async def _serve(self, connection: ServerConnection) -> None:
        viewer, token = self._admitted.pop(connection, (None, None))
        if viewer is None:
            return
        client = _Client(connection, viewer, token)
        self.clients.add(client)
        log.info("live view: %s watching from %s", viewer.name, connection.remote_address[0])
        client.control.append(json.dumps({"op": "serverInfo", "name": "twohr", "capabilities": [],
                                          "supportedEncodings": [], "metadata": {}, "sessionId": self._session}))
        visible = [c.advert for c in list(self.channels.values()) if viewer.sees(c.topic)]
        if visible:
            client.control.append(json.dumps({"op": "advertise", "channels": visible}))
        client.wake.set()
        writer = asyncio.create_task(self._write(client))
        try:
            async for message in connection:
                if isinstance(message, str):
                    self._on_request(client, message)
        except ConnectionClosed:
            pass
        finally:
            self.clients.discard(client)
            self._update_subscribed()
            writer.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await writer

    def _on_request(self, client: _Client, text: str) -> None:
        """A viewer's subscribe or unsubscribe; a channel it may not see is as unknown as one that does not exist.
        A request with an id that is not a u32 changes nothing and is answered "malformed request"."""
        try:
            request = json.loads(text)
            op = request["op"]
            if op == "subscribe":
                wanted = [(_u32(s["channelId"]), _u32(s["id"])) for s in request["subscriptions"]]
                by_id = {c.id: c for c in list(self.channels.values())}
                for channel_id, subscription in wanted:
                    channel = by_id.get(channel_id)
                    if channel is None or not client.viewer.sees(channel.topic):
                        self._status(client, f"Unknown channel ID: {channel_id}")
                    else:
                        client.subscriptions[channel.id] = subscription
            elif op == "unsubscribe":
                ended = {_u32(i) for i in request["subscriptionIds"]}
                client.subscriptions = {c: s for c, s in client.subscriptions.items() if s not in ended}
        except (ValueError, KeyError, TypeError):
            self._status(client, "malformed request")
        self._update_subscribed()

    def _status(self, client: _Client, message: str) -> None:
        client.control.append(json.dumps({"op": "status", "level": 2, "message": message}))
        client.wake.set()

    def _update_subscribed(self) -> None:
        self._subscribed = {channel for client in self.clients for channel in client.subscriptions}

    def _advertise(self, channels: list[_Channel]) -> None:
        for client in self.clients:
            visible = [c.advert for c in channels if client.viewer.sees(c.topic)]
            if visible:
                client.control.append(json.dumps({"op": "advertise", "channels": visible}))
                client.wake.set()

    def backlog(self) -> int:
        """Messages logged that wait for a viewer: those not yet handed to the viewers' queues, and the longest
        queue."""
        return sum(len(batch) for batch in list(self._outbox)) + max(
            (len(client.data) for client in list(self.clients)), default=0)

    def _deliver(self) -> None:
        with self._outbox_lock:
            batches, self._delivering = list(self._outbox), False
            self._outbox.clear()
        for client in self.clients:
            queued = False
            for channel, log_time, payload in (message for batch in batches for message in batch):
                subscription = client.subscriptions.get(channel)
                if subscription is None:
                    continue
                client.data.append((subscription, log_time, payload))
                client.data_bytes += len(payload)
                queued = True
            while len(client.data) > VIEWER_BACKLOG or client.data_bytes > VIEWER_BACKLOG_BYTES:
                client.data_bytes -= len(client.data.popleft()[2])
                client.dropped += 1
            if queued:
                client.wake.set()

    async def _write(self, client: _Client) -> None:
        """Send a viewer what waits for it, control messages first; a slow viewer waits here, alone."""
        with contextlib.suppress(ConnectionClosed):
            while True:
                await client.wake.wait()
                client.wake.clear()
                while client.control or client.data:
                    if client.control:
                        await client.connection.send(client.control.popleft())
                        continue
                    subscription, log_time, payload = client.data.popleft()
                    client.data_bytes -= len(payload)
                    await client.connection.send(MESSAGE_DATA.pack(1, subscription, log_time) + payload)

    async def _recheck_tokens(self) -> None:
        """Close the connections whose token is no longer valid (a robot revoked since it connected, or expired). A
        check that fails counts as a refusal: that viewer is closed, the others are checked, and the task goes on."""
        while True:
            await asyncio.sleep(RECHECK_S)
            for client in list(self.clients):
                try:
                    valid = self.authorize(client.token) is not None
                except Exception:
                    log.exception("live view: checking %s's token failed: closing its connection", client.viewer.name)
                    valid = False
                if not valid:
                    log.warning("live view: %s's token is no longer valid: closing its connection", client.viewer.name)
                    self.clients.discard(client)
                    self._update_subscribed()
                    asyncio.create_task(client.connection.close(1008, "token no longer valid"))

    def _idle(self) -> bool:
        return not self._outbox and all(not client.control and not client.data for client in self.clients)

    async def _shutdown(self, drain_s: float) -> None:
        deadline = time.monotonic() + drain_s
        while not self._idle() and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
        if self._recheck is not None:
            self._recheck.cancel()
        self.server.close()  # closes every connection: what was sent is delivered before the close frame
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(self.server.wait_closed(), 5)
        tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    def _stop_loop(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(timeout=2)
        self.loop.close()

    def close(self, drain_s: float = 2.0) -> None:
        """Stop serving, once every viewer got what was logged (waiting at most ``drain_s`` for slow ones)."""
        with contextlib.suppress(Exception):
            asyncio.run_coroutine_threadsafe(self._shutdown(drain_s), self.loop).result(drain_s + 10)
        self._stop_loop()


def _u32(value) -> int:
    """A subscription or channel id from a viewer: an integer that fits the wire's u32 (ValueError otherwise)."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_SUBSCRIPTION_ID:
        raise ValueError(f"not an id: {value!r}")
    return value


def _full(viewer: Viewer, watching: list[Viewer]) -> str | None:
    """Why ``viewer`` cannot be let in beside those ``watching`` (None: it can): the operator has
    :data:`OPERATOR_VIEWERS` of its own; a robot at most :data:`VIEWERS_PER_ROBOT`, and all robots together
    :data:`MAX_VIEWERS`."""
    if viewer is EVERYTHING:
        if sum(other is EVERYTHING for other in watching) >= OPERATOR_VIEWERS:
            return f"the operator has {OPERATOR_VIEWERS} viewers open, the most it may"
        return None
    if sum(other.name == viewer.name for other in watching) >= VIEWERS_PER_ROBOT:
        return f"{viewer.name} has {VIEWERS_PER_ROBOT} viewers open, the most a robot may"
    if sum(other is not EVERYTHING for other in watching) >= MAX_VIEWERS:
        return f"the robots have {MAX_VIEWERS} viewers open, the most they may together"
    return None


class FoxgloveClient:
    """A Foxglove WebSocket client on its own thread: it subscribes to every channel the server advertises and
    counts the messages of each topic (and keeps the latest one). For tests, the bench and quick checks.

    ``token`` goes into the URL as ``?token=``; a ``wss://`` URL is verified with ``cafile`` (the fleet's
    ``ca.crt``), else with the system's roots. A refused upgrade raises ``websockets.exceptions.InvalidStatus``."""

    def __init__(self, url: str, subprotocol: str = "foxglove.websocket.v1", timeout: float = 30.0,
                 token: str | None = None, cafile: str | Path | None = None) -> None:
        if token is not None:
            url += ("&" if urlsplit(url).query else ("?" if urlsplit(url).path else "/?")) + urlencode({"token": token})
        tls = ssl.create_default_context(cafile=str(cafile) if cafile else None) if url.startswith("wss:") else None
        # the protocol's name in its spec is "foxglove.websocket.v1"; foxglove-sdk calls it "foxglove.sdk.v1"
        self.ws = connect(url, subprotocols=[subprotocol], max_size=None, open_timeout=timeout, ssl=tls,
                          compression=None).__enter__()
        if self.ws.subprotocol != subprotocol:
            raise ConnectionError(f"the live view answered with subprotocol {self.ws.subprotocol!r}, not "
                                  f"{subprotocol!r}")
        self.channels: dict[int, dict] = {}
        self.subscriptions: dict[int, int] = {}
        self.counts: dict[str, int] = {}
        self.latest: dict[str, bytes] = {}
        self.server_info: dict | None = None
        self.statuses: list[str] = []
        self.thread = threading.Thread(target=self._run, name="foxglove-client", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            for message in self.ws:
                if isinstance(message, str):
                    body = json.loads(message)
                    if body["op"] == "serverInfo":
                        self.server_info = body
                    elif body["op"] == "advertise":
                        for channel in body["channels"]:
                            self.channels[channel["id"]] = channel
                        self._subscribe([channel["id"] for channel in body["channels"]])
                    elif body["op"] == "status":
                        self.statuses.append(body.get("message", ""))
                elif message[0] == 1:  # message data: opcode, subscription id (u32), log time (u64), payload
                    subscription = struct.unpack_from("<I", message, 1)[0]
                    topic = self.channels[self.subscriptions[subscription]]["topic"]
                    self.counts[topic] = self.counts.get(topic, 0) + 1
                    self.latest[topic] = bytes(message[13:])
        except ConnectionClosed:
            pass

    def _subscribe(self, channel_ids: list[int]) -> None:
        new = []
        for channel_id in channel_ids:
            subscription = len(self.subscriptions) + 1
            self.subscriptions[subscription] = channel_id
            new.append({"id": subscription, "channelId": channel_id})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))

    def subscribe(self, channel_id: int) -> None:
        """Ask for a channel by id (whether or not it was advertised to this client)."""
        self.channels.setdefault(channel_id, {"id": channel_id, "topic": f"?{channel_id}", "schemaName": "?"})
        self._subscribe([channel_id])

    @property
    def closed(self) -> bool:
        """Whether the server closed this connection."""
        return not self.thread.is_alive()

    def topics(self) -> dict[str, str]:
        """Advertised topic -> schema name."""
        return {c["topic"]: c["schemaName"] for c in list(self.channels.values()) if "schema" in c}

    def decode(self, topic: str):
        """The latest message on ``topic``, decoded with the protobuf schema the server advertised."""
        channel = next(c for c in list(self.channels.values()) if c["topic"] == topic)
        pool = descriptor_pool.DescriptorPool()
        for file in descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"])).file:
            pool.Add(file)
        cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))
        return cls.FromString(self.latest[topic])

    def close(self) -> None:
        self.ws.close()
        self.thread.join(5)
