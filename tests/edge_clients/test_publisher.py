"""SensorPublisher on real Zenoh: wire format, liveliness per sensor, shared flags."""

from __future__ import annotations

import queue

import msgpack
import numpy as np
import pytest
import typer
import zenoh

from edge_clients.cli import DEFAULT_CONNECT, zenoh_settings
from edge_clients.publisher import RateMeter, SensorPublisher
from proto import KeypointMessage, Person, decode, keys
from proto.transport import ZenohSettings, free_port, open_session


def test_packed_wire_format_and_liveliness_tokens():
    ep = f"tcp/127.0.0.1:{free_port()}"
    backend = open_session(ZenohSettings(listen=(ep,)))
    sensor_side = open_session(ZenohSettings(connect=(ep,)))
    got: queue.Queue = queue.Queue()
    alive: queue.Queue = queue.Queue()
    sub = backend.declare_subscriber(keys.all_keypoints("s1"), lambda s: got.put(s.payload.to_bytes()))
    lsub = backend.liveliness().declare_subscriber(
        keys.all_alive("s1"), lambda s: alive.put((str(s.key_expr), s.kind == zenoh.SampleKind.PUT)))
    try:
        pub = SensorPublisher(sensor_side, "s1")
        assert pub.wait_matched(["cam_1"], 30)
        assert alive.get(timeout=30) == (keys.alive("s1", "cam_1"), True)
        kp = np.zeros((17, 3))
        kp[:, 0] = np.arange(17) + 0.1  # not float32-exact: the wire rounds it
        kp[:, 2] = 1.0
        msg = KeypointMessage(sensor="cam_1", seq=7, stamp=1.7e9 + 0.123456789, size=(848, 480),
                              persons=(Person(kp=kp),))
        pub.publish(msg)
        raw = got.get(timeout=30)
        d = msgpack.unpackb(raw)
        assert isinstance(d["persons"][0]["kp"], bytes) and len(d["persons"][0]["kp"]) == 17 * 3 * 4
        back = decode(raw)
        assert back.stamp == msg.stamp and back.seq == 7  # float64 stamp survives exactly
        assert np.array_equal(back.persons[0].kp, kp.astype(np.float32).astype(np.float64))
        assert pub.stats["cam_1"].sent == 1 and pub.total == 1
        pub.close()
        assert alive.get(timeout=30) == (keys.alive("s1", "cam_1"), False), "token gone when the sensor stops"
    finally:
        lsub.undeclare()
        sub.undeclare()
        sensor_side.close()
        backend.close()


def test_bad_sensor_names_are_refused_before_publishing():
    with pytest.raises(ValueError, match="sensor"):
        SensorPublisher(session=None, site="s1").declare("cam/1")


def test_shared_flags_default_to_connecting_to_the_local_backend():
    s = zenoh_settings(None, None, "peer", None)
    assert s.connect == (DEFAULT_CONNECT,) and s.listen == () and not s.multicast_scouting
    s = zenoh_settings(["tcp/0.0.0.0:7448"], None, "peer", None)
    assert s.connect == () and s.listen == ("tcp/0.0.0.0:7448",)
    s = zenoh_settings(None, ["tcp/10.0.0.5:7447", "tcp/10.0.0.6:7447"], "client", None)
    assert s.connect == ("tcp/10.0.0.5:7447", "tcp/10.0.0.6:7447") and s.mode == "client"
    with pytest.raises(typer.BadParameter):
        zenoh_settings(None, None, "server", None)


def test_rate_meter():
    r = RateMeter(window=1.0)
    for k in range(31):
        r.tick(100.0 + k / 30)
    assert r.rate(101.0) == pytest.approx(30.0, rel=0.01)
    assert r.rate(103.0) == 0.0
