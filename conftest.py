"""Shared fixtures: the real dev sequence and models from ../shared, and small synthetic sequences."""

from __future__ import annotations

from pathlib import Path

import pytest

from twohr.bus import free_port

REPO = Path(__file__).resolve().parent
SHARED = REPO.parent / "shared"
DEV_SEQUENCE = SHARED / "data" / "rgbd_bonn_crowd_dev"
MODEL_MIRROR = SHARED / "models"


@pytest.fixture(scope="session")
def dev_sequence() -> Path:
    if not DEV_SEQUENCE.is_dir():
        pytest.fail(f"the real dev sequence is required at {DEV_SEQUENCE} (../shared beside the repo)")
    return DEV_SEQUENCE


@pytest.fixture(scope="session")
def model_mirror() -> Path:
    if not MODEL_MIRROR.is_dir():
        pytest.fail(f"the model mirror is required at {MODEL_MIRROR}")
    return MODEL_MIRROR


@pytest.fixture(scope="session")
def synthetic_sequence(tmp_path_factory) -> Path:
    """60 frames at 320x240 with one moving occluder; exact depth and ground truth."""
    from twohr.synthetic import SyntheticSpec, generate

    return generate(tmp_path_factory.mktemp("synth") / "synthetic_room", SyntheticSpec(frames=60))


@pytest.fixture(scope="session")
def static_synthetic_sequence(tmp_path_factory) -> Path:
    """30 frames, no moving objects."""
    from twohr.synthetic import SyntheticSpec, generate

    return generate(tmp_path_factory.mktemp("synth_static") / "synthetic_static",
                    SyntheticSpec(frames=30, occluders=0, seed=3))


@pytest.fixture(scope="session")
def zenoh_router():
    """A real Zenoh router on a free loopback port; yields its endpoint."""
    from twohr.bus import start_router

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = start_router([endpoint])
    yield endpoint
    router.close()


@pytest.fixture
def bus_config(zenoh_router):
    from twohr.bus import BusConfig

    return BusConfig(connect=[zenoh_router])


class FoxgloveListener:
    """A Foxglove WebSocket client (subprotocol ``foxglove.websocket.v1``) on its own thread: it subscribes to
    every channel the server advertises and counts the messages of each topic (and keeps the latest one)."""

    def __init__(self, url: str, subprotocol: str = "foxglove.websocket.v1", timeout: float = 10.0) -> None:
        import threading

        from websockets.sync.client import connect

        # the protocol's name in its spec is "foxglove.websocket.v1"; foxglove-sdk 0.30 calls it "foxglove.sdk.v1"
        self.ws = connect(url, subprotocols=[subprotocol], max_size=None, open_timeout=timeout).__enter__()
        assert self.ws.subprotocol == subprotocol
        self.channels: dict[int, dict] = {}
        self.subscriptions: dict[int, int] = {}
        self.counts: dict[str, int] = {}
        self.latest: dict[str, bytes] = {}
        self.server_info: dict | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        import json
        import struct

        from websockets.exceptions import ConnectionClosed

        try:
            for message in self.ws:
                if isinstance(message, str):
                    body = json.loads(message)
                    if body["op"] == "serverInfo":
                        self.server_info = body
                    elif body["op"] == "advertise":
                        new = []
                        for channel in body["channels"]:
                            self.channels[channel["id"]] = channel
                            subscription = len(self.subscriptions) + 1
                            self.subscriptions[subscription] = channel["id"]
                            new.append({"id": subscription, "channelId": channel["id"]})
                        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                elif message[0] == 1:  # message data: opcode, subscription id (u32), log time (u64), payload
                    subscription = struct.unpack_from("<I", message, 1)[0]
                    topic = self.channels[self.subscriptions[subscription]]["topic"]
                    self.counts[topic] = self.counts.get(topic, 0) + 1
                    self.latest[topic] = bytes(message[13:])
        except ConnectionClosed:
            pass

    def topics(self) -> dict[str, str]:
        """Advertised topic -> schema name."""
        return {c["topic"]: c["schemaName"] for c in list(self.channels.values())}

    def decode(self, topic: str):
        """The latest message on ``topic``, decoded with the protobuf schema the server advertised."""
        import base64

        from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

        channel = next(c for c in list(self.channels.values()) if c["topic"] == topic)
        pool = descriptor_pool.DescriptorPool()
        for file in descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"])).file:
            pool.Add(file)
        cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))
        return cls.FromString(self.latest[topic])

    def close(self) -> None:
        self.ws.close()
        self.thread.join(5)


@pytest.fixture
def foxglove_listener():
    """Opens :class:`FoxgloveListener` clients on a URL; closes them after the test."""
    opened = []

    def open_listener(url: str, subprotocol: str = "foxglove.websocket.v1") -> FoxgloveListener:
        opened.append(FoxgloveListener(url, subprotocol))
        return opened[-1]

    yield open_listener
    for listener in opened:
        listener.close()
