"""The map store on the bus (``twohr/maps/<name>``, ``twohr/maps/<name>/save``) against a real Zenoh router: a save
that waits on the store does not hold up the gateway's other queries.

The wait is made deterministic rather than slow: the test holds the store's lock (the one a save takes while
another upload or save is under way), so the save cannot finish until the test lets it."""

from __future__ import annotations

import json
import time

import pytest

from twohr import keys
from twohr.bus import open_session
from twohr.dataset import RGBDSequence
from twohr.mapfile import _STORE_LOCK, MapStore, write_map
from twohr_services.gateway.bus import GatewayBus
from twohr_services.gateway.sessions import SessionTable
from twohr_services.gateway.settings import GatewaySettings


@pytest.fixture
def map_gateway(bus_config, tmp_path, tiny_map, dev_sequence):
    """A gateway bus keeping a map store with one map (``lab``), and a client session on the same router."""
    maps = tmp_path / "maps"
    write_map(maps / "lab.map", tiny_map("lab", RGBDSequence(dev_sequence).camera))
    bus = GatewayBus(GatewaySettings(maps=maps, bus=bus_config), SessionTable())
    bus.start()
    client = open_session(bus_config)
    try:
        deadline = time.monotonic() + 30
        while not read_map_bytes(client, "lab", timeout=1.0):  # the queryables' routes reached the router
            assert time.monotonic() < deadline, "the gateway's map store never answered"
        yield client, maps
    finally:
        client.close()
        bus.close()


def read_map_bytes(client, name: str, timeout: float) -> bytes | None:
    """The bytes ``twohr/maps/<name>`` answers with, None when no good reply came within ``timeout``."""
    replies = list(client.get(keys.map_key(name), timeout=timeout))
    return next((r.ok.payload.to_bytes() for r in replies if r.ok is not None), None)


def test_a_save_waiting_on_the_store_holds_up_no_other_map_query(map_gateway):
    """Zenoh hands a queryable's queries to one callback thread, one after the other: a save doing its file I/O
    there kept every later save waiting (a refused one included), and a full channel would stall the session."""
    client, maps = map_gateway
    data = (maps / "lab.map").read_bytes()
    with _STORE_LOCK:  # another save is under way: this one must wait for it
        saving = client.get(keys.map_key("lab", save=True), payload=data, timeout=120)
        # sent after the save, on the same link: they reach the gateway after it
        refused = list(client.get(keys.map_key("lab", save=True), payload=b"not a map", timeout=20))
        assert [r.err is not None for r in refused] == [True], "a bad save waited for a save in progress"
        assert "not a twohr map" in refused[0].err.payload.to_string()
        assert read_map_bytes(client, "lab", timeout=20) == data, "a map read waited for a save in progress"
        assert saving.try_recv() is None, "the save finished while the store was locked"
    replies = list(saving)  # the lock is free: the save goes through and is answered
    assert len(replies) == 1 and replies[0].ok is not None, [r.err.payload.to_string() for r in replies if r.err]
    entry = json.loads(replies[0].ok.payload.to_bytes())
    assert entry["name"] == "lab" and entry["version"] == 2
    assert MapStore(maps).versions("lab") == [maps / "lab.v1.map"]


def test_a_bad_save_and_a_missing_map_are_answered_with_errors(map_gateway):
    client, maps = map_gateway
    refused = list(client.get(keys.map_key("lab", save=True), payload=b"not a map", timeout=20))
    assert len(refused) == 1 and refused[0].err is not None
    assert "not a twohr map" in refused[0].err.payload.to_string()
    missing = list(client.get(keys.map_key("nowhere"), timeout=20))
    assert len(missing) == 1 and missing[0].err is not None
    assert "no map named 'nowhere'" in missing[0].err.payload.to_string()
    assert not MapStore(maps).versions("lab")
