"""A Foxglove WebSocket server (foxglove-sdk's ``start_server``) for the live view of any number of robots.

Open it in Foxglove: ``https://app.foxglove.dev/?ds=foxglove-websocket&ds.url=ws://HOST:PORT``. Channels are
advertised as their first message arrives (or all of a robot's at once, :meth:`LiveView.advertise`); the
messages come from :class:`~.foxglove_convert.FoxgloveConverter` (the same as in recordings). The gateway feeds
it from the bus, ``twohr run --view`` from the pipeline.

foxglove-sdk 0.30 names the WebSocket subprotocol ``foxglove.sdk.v1`` and turns away clients that offer only
its former, otherwise identical name ``foxglove.websocket.v1`` (Lichtblick, older Foxglove Studio, the ws-protocol
clients). :class:`SubprotocolBridge` in front of the SDK's server accepts both names.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import logging
import re
import struct
import threading
import time

import foxglove
import foxglove.channels
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from .errors import TwohrError
from .foxglove_convert import TOPIC_TYPES, FoxgloveConverter, topics

SDK_PROTOCOL = b"foxglove.sdk.v1"
LEGACY_PROTOCOL = b"foxglove.websocket.v1"
# foxglove-sdk 0.30 sends a new channel's "advertise" before it records the channel as advertised to that client
# (ConnectedClient::advertise_channels), so a client that subscribes at once can be told "Unknown channel ID"
# and never get that channel. Holding what clients send for a moment closes that window; clients only send
# subscribe/unsubscribe here, so nothing else waits on it.
CLIENT_HOLD_S = 0.02
UNKNOWN_CHANNEL = re.compile(r"Unknown channel ID: (\d+)")


class SubprotocolBridge:
    """A TCP relay on ``host:port`` to the SDK's server on ``127.0.0.1:target_port`` that renames the legacy
    subprotocol in the opening handshake (both ways) and then passes the bytes through untouched."""

    def __init__(self, host: str, port: int, target_port: int) -> None:
        self.target_port = target_port
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="foxglove-bridge", daemon=True)
        self.thread.start()
        try:
            self.server = asyncio.run_coroutine_threadsafe(
                asyncio.start_server(self._relay, host, port), self.loop).result(10)
        except OSError as exc:
            self.loop.call_soon_threadsafe(self.loop.stop)
            raise TwohrError(f"live view: cannot listen on {host}:{port}: {exc.strerror or exc}") from None
        self.port = self.server.sockets[0].getsockname()[1]

    async def _relay(self, client_in: asyncio.StreamReader, client_out: asyncio.StreamWriter) -> None:
        server_out = None
        try:
            request = await client_in.readuntil(b"\r\n\r\n")
            legacy = LEGACY_PROTOCOL in request and SDK_PROTOCOL not in request
            if legacy:
                request = request.replace(LEGACY_PROTOCOL, SDK_PROTOCOL)
            server_in, server_out = await asyncio.open_connection("127.0.0.1", self.target_port)
            server_out.write(request)
            response = await server_in.readuntil(b"\r\n\r\n")
            client_out.write(response.replace(SDK_PROTOCOL, LEGACY_PROTOCOL) if legacy else response)
            await asyncio.gather(self._pipe(client_in, server_out, CLIENT_HOLD_S), self._pipe(server_in, client_out))
        except (OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError):
            pass  # a client that went away or never spoke HTTP
        finally:
            for writer in (client_out, server_out):
                if writer is not None:
                    writer.close()

    @staticmethod
    async def _pipe(source: asyncio.StreamReader, sink: asyncio.StreamWriter, hold_s: float = 0.0) -> None:
        with contextlib.suppress(OSError):
            while data := await source.read(1 << 16):
                if hold_s:
                    await asyncio.sleep(hold_s)
                sink.write(data)
                await sink.drain()
        with contextlib.suppress(OSError):
            sink.close()

    async def _shutdown(self) -> None:
        self.server.close()
        tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            asyncio.run_coroutine_threadsafe(self._shutdown(), self.loop).result(5)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(timeout=2)
        self.loop.close()


def view_url(host: str, port: int) -> str:
    """The Foxglove app's address that opens this live view."""
    return f"https://app.foxglove.dev/?ds=foxglove-websocket&ds.url=ws://{host}:{port}"


class LiveView:
    """A Foxglove WebSocket server on ``host:port`` (port 0 picks a free one, see :attr:`port`)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, jpeg_quality: int | None = None,
                 path_every: int = 5) -> None:
        logging.getLogger("foxglove").setLevel(logging.WARNING)  # not a line per client and start
        self.context = foxglove.Context()  # its own channels and sinks: no other logging reaches this server
        self.server = foxglove.start_server(name="twohr", host="127.0.0.1", port=0, context=self.context)
        try:
            self.bridge = SubprotocolBridge(host, port, self.server.port)
        except TwohrError:
            self.server.stop()
            raise
        self.host, self.port = host, self.bridge.port
        self.converter = FoxgloveConverter(jpeg_quality, path_every)
        self.channels: dict[str, object] = {}
        self.lock = threading.Lock()
        self.sent = 0

    @property
    def url(self) -> str:
        return view_url(self.host, self.port)

    def _channel(self, topic: str, message_type: type):
        channel = self.channels.get(topic)
        if channel is None:
            channel_class = getattr(foxglove.channels, message_type.__name__ + "Channel")
            channel = self.channels[topic] = channel_class(topic, context=self.context)
        return channel

    def advertise(self, robot_id: str) -> None:
        """Advertise a robot's channels now, so that a client can subscribe before its first frame."""
        with self.lock:
            for kind, topic in topics(robot_id).items():
                self._channel(topic, TOPIC_TYPES[kind])

    def log(self, messages: list[tuple[str, object]]) -> None:
        """Send ``(topic, Foxglove message)`` pairs, advertising each topic's channel on first use."""
        with self.lock:
            for topic, message in messages:
                self._channel(topic, type(message)).log(message)
                self.sent += 1

    def reset(self, robot_id: str) -> None:
        """A robot starts a new session: its path starts again."""
        with self.lock:
            self.converter.reset(robot_id)

    def convert_and_log(self, payload: bytes) -> None:
        """Show one bus message (raises ``MessageError`` if it is malformed)."""
        with self.lock:
            messages = self.converter.convert(payload)
        self.log(messages)

    def close(self, drain_s: float = 0.5) -> None:
        """Stop serving, after ``drain_s`` for the relay to hand viewers the last messages it holds."""
        if self.sent:
            time.sleep(drain_s)
        self.bridge.close()
        self.server.stop()


class FoxgloveClient:
    """A Foxglove WebSocket client on its own thread: it subscribes to every channel the server advertises and
    counts the messages of each topic (and keeps the latest one). For tests, the bench and quick checks.

    A subscription the server refuses with "Unknown channel ID" (see :data:`CLIENT_HOLD_S`) is sent again after a
    moment, and counted in :attr:`resubscribed`."""

    def __init__(self, url: str, subprotocol: str = "foxglove.websocket.v1", timeout: float = 10.0) -> None:
        # the protocol's name in its spec is "foxglove.websocket.v1"; foxglove-sdk 0.30 calls it "foxglove.sdk.v1"
        self.ws = connect(url, subprotocols=[subprotocol], max_size=None, open_timeout=timeout).__enter__()
        if self.ws.subprotocol != subprotocol:
            raise ConnectionError(f"{url} answered with subprotocol {self.ws.subprotocol!r}, not {subprotocol!r}")
        self.channels: dict[int, dict] = {}
        self.subscriptions: dict[int, int] = {}
        self.counts: dict[str, int] = {}
        self.latest: dict[str, bytes] = {}
        self.server_info: dict | None = None
        self.resubscribed = 0
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
                    elif body["op"] == "status" and (refused := UNKNOWN_CHANNEL.fullmatch(body.get("message", ""))):
                        channel_id = int(refused.group(1))
                        if channel_id in self.channels and self.resubscribed < len(self.channels):
                            time.sleep(0.05)
                            self.resubscribed += 1
                            self._subscribe([channel_id])
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

    def topics(self) -> dict[str, str]:
        """Advertised topic -> schema name."""
        return {c["topic"]: c["schemaName"] for c in list(self.channels.values())}

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
