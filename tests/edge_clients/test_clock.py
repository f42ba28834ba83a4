"""NTP offset checks against a tiny NTP server on a real UDP socket on 127.0.0.1."""

from __future__ import annotations

import re

import socket
import struct
import threading
import time

import pytest

pytest.importorskip("ntplib")

from edge_clients.clock import Clock, NtpClock, make_clock  # noqa: E402

pytestmark = pytest.mark.serial  # offsets measured by round trips on loopback
NTP_EPOCH = 2208988800  # 1900 → 1970


def _ts(t: float) -> bytes:
    t += NTP_EPOCH
    sec = int(t)
    return struct.pack("!II", sec, int((t - sec) * 2**32))


class TinyNtpServer:
    """Answers NTP v3 client requests with its clock = local clock + ``offset``."""

    def __init__(self, offset: float):
        self.offset = offset
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]
        self.requests = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                data, addr = self.sock.recvfrom(512)
            except socket.timeout:
                continue
            recv = time.time() + self.offset
            if len(data) < 48:
                continue
            self.requests += 1
            header = struct.pack("!BBbb", (0 << 6) | (3 << 3) | 4, 1, 6, -20)  # LI 0, v3, server; stratum 1
            root = struct.pack("!II", 0, 0) + b"LOCL"
            reply = header + root + _ts(recv) + data[40:48] + _ts(recv) + _ts(time.time() + self.offset)
            self.sock.sendto(reply, addr)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.sock.close()


@pytest.fixture
def ntp_server():
    server = TinyNtpServer(offset=0.25)
    yield server
    server.close()


def test_offset_is_measured_and_reported_but_not_applied_by_default(ntp_server):
    with make_clock(f"127.0.0.1:{ntp_server.port}", interval=60) as clock:
        assert isinstance(clock, NtpClock)
        assert clock.wait_first(5)
        assert clock.offset() == pytest.approx(0.25, abs=0.01)
        assert abs(clock.now() - time.time()) < 0.01
        status = clock.status()
        m = re.search(r"offset ([+-][0-9.]+) ms", status)
        assert m is not None and abs(float(m.group(1)) - 250.0) < 15.0, status  # a busy host adds a few ms
        assert "not corrected" in status and "beyond" in status


def test_clock_correct_applies_the_offset(ntp_server):
    with make_clock(f"127.0.0.1:{ntp_server.port}", correct=True, interval=0.05) as clock:
        assert clock.wait_first(5)
        assert clock.now() - time.time() == pytest.approx(0.25, abs=0.01)
        # Periodic checks keep running.
        deadline = time.monotonic() + 5
        while ntp_server.requests < 3 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert ntp_server.requests >= 3
        assert "(corrected)" in clock.status()


def test_an_unreachable_server_is_reported_and_nothing_is_corrected():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # bound but silent: requests time out
        clock = NtpClock("127.0.0.1", port=port, correct=True, timeout=0.2, interval=60)
        try:
            assert clock.wait_first(5)
            assert clock.offset() is None
            assert abs(clock.now() - time.time()) < 0.01
            assert "no answer" in clock.status()
        finally:
            clock.close()


def test_make_clock_without_ntp():
    assert type(make_clock(None)) is Clock
    with pytest.raises(ValueError, match="--clock-correct needs --ntp-server"):
        make_clock(None, correct=True)
