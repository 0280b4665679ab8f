"""A Foxglove WebSocket server (foxglove-sdk's ``start_server``) for the live view of any number of robots.

Open it in Foxglove: ``https://app.foxglove.dev/?ds=foxglove-websocket&ds.url=ws://HOST:PORT``. Channels are
advertised as their first message arrives; the messages come from :class:`~.foxglove_convert.FoxgloveConverter`
(the same as in recordings). The gateway feeds it from the bus, ``twohr run --view`` from the pipeline.
"""

from __future__ import annotations

import threading

import foxglove
import foxglove.channels

from .foxglove_convert import TOPIC_TYPES, FoxgloveConverter, topics


def view_url(host: str, port: int) -> str:
    """The Foxglove app's address that opens this live view."""
    return f"https://app.foxglove.dev/?ds=foxglove-websocket&ds.url=ws://{host}:{port}"


class LiveView:
    """A Foxglove WebSocket server on ``host:port`` (port 0 picks a free one, see :attr:`port`)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, jpeg_quality: int | None = None,
                 path_every: int = 5) -> None:
        self.context = foxglove.Context()  # its own channels and sinks: no other logging reaches this server
        self.server = foxglove.start_server(name="twohr", host=host, port=port, context=self.context)
        self.host, self.port = host, self.server.port
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

    def close(self) -> None:
        self.server.stop()
