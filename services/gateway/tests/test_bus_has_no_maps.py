"""The maps and the sessions' map snapshots on the bus are the map room's (``twohr_services.mapserver``): the
gateway's bus, given a map store, answers no map query, takes no save and keeps no snapshot, against a real Zenoh
router."""

from __future__ import annotations

import dataclasses
import time

from twohr import keys
from twohr.bus import open_session
from twohr_services.gateway.bus import GatewayBus
from twohr_services.gateway.sessions import Session, SessionTable
from twohr_services.gateway.settings import GatewaySettings


def test_the_gateway_serves_no_map_key_and_keeps_no_snapshot(bus_config, tmp_path, tiny_map, dev_sequence):
    from twohr.dataset import RGBDSequence
    from twohr.mapfile import encode_map, write_map

    maps = tmp_path / "maps"
    made = tiny_map("lab", RGBDSequence(dev_sequence).camera)
    write_map(maps / "lab.map", made)
    bus = GatewayBus(GatewaySettings(maps=maps, bus=bus_config), SessionTable())
    bus.start()
    client = open_session(bus_config)
    try:
        time.sleep(1.0)  # the gateway's declarations reached the router
        client.put(keys.snapshot_key("r1"), encode_map(made), attachment="s1")
        for key, payload, attachment in ((keys.map_key("lab"), None, None),
                                         (keys.map_key("lab", save=True), encode_map(made), None),
                                         (keys.snapshot_key("r1"), None, "s1")):
            replies = list(client.get(key, payload=payload, attachment=attachment, timeout=2.0))
            assert replies == [], (key, replies)
    finally:
        client.close()
        bus.close()
    assert "snapshot" not in {field.name for field in dataclasses.fields(Session)}
    assert sorted(p.name for p in maps.iterdir()) == ["lab.map"]  # no save landed
