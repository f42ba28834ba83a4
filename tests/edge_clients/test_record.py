"""`extrcal record` as a real process: flushed while running, rejects counted, clean stop on SIGTERM."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import msgpack
import numpy as np
import pytest

from edge_clients.publisher import SensorPublisher
from proto import KeypointMessage, Person, keys, read_recording
from proto.transport import ZenohSettings, free_port, open_session


def msg(seq: int, sensor: str = "cam_0") -> KeypointMessage:
    kp = np.zeros((17, 3))
    kp[:, 0], kp[:, 1], kp[:, 2] = np.arange(17) * 10.0, 100.0 + seq, 0.5
    return KeypointMessage(sensor=sensor, seq=seq, stamp=1.7e9 + seq / 30, size=(640, 480), persons=(Person(kp=kp),))


def wait_for(pred, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = pred()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.mark.serial  # the flush is timed on the wall clock
def test_record_process_flushes_every_second_counts_rejects_and_stops_on_sigterm(tmp_path):
    port = free_port()
    out = tmp_path / "rec.jsonl"
    proc = subprocess.Popen(
        [sys.executable, "-c", "from backend.cli import main; main()", "record", "--out", str(out), "-q",
         "--zenoh-listen", f"tcp/127.0.0.1:{port}", "--site", "lab"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONWARNINGS": "error"},
    )
    session = open_session(ZenohSettings(connect=(f"tcp/127.0.0.1:{port}",)))
    try:
        with SensorPublisher(session, "lab", block=True) as pub:
            # The recorder's subscriber is the `started` state.
            assert pub.wait_matched(["cam_0", "cam_1"], 20), proc.stderr.read() if proc.poll() is not None else ""
            for k in range(20):
                pub.publish(msg(k))
            pub.publish(msg(0, "cam_1"))
            # Bad input on the wire: garbage, a NaN keypoint, a message on another sensor's key.
            session.put(keys.keypoints("lab", "cam_0"), b"\xc1garbage")
            d = {"v": 1, "sensor": "cam_0", "seq": 99, "stamp": 1.7e9, "size": [640, 480],
                 "persons": [{"kp": [[float("nan"), 1.0, 1.0]] * 17}]}
            session.put(keys.keypoints("lab", "cam_0"), msgpack.packb(d))
            session.put(keys.keypoints("lab", "cam_0"), msgpack.packb({**d, "sensor": "cam_9", "persons": []}))
            t_sent = time.monotonic()
            # Flushed within about a second while still running: a crash now would lose nothing.
            wait_for(lambda: out.exists() and len(out.read_text().splitlines()) == 21, 5, "21 flushed lines")
            assert time.monotonic() - t_sent < 2.5
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
        session.close()
    assert proc.returncode == 0, stderr
    assert "wrote 21 messages from 2 sensors" in stdout
    assert "rejected 3 invalid messages" in stdout
    got = list(read_recording(out))
    assert [m.seq for m in got if m.sensor == "cam_0"] == list(range(20))
    assert got[5] == msg(5)


def test_record_refuses_to_overwrite(tmp_path):
    out = tmp_path / "rec.jsonl"
    out.write_text("keep me\n")
    res = subprocess.run([sys.executable, "-c", "from backend.cli import main; main()", "record", "--out", str(out)],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and "exists" in res.stderr
    assert out.read_text() == "keep me\n"
