"""The HTTP server runs on its own thread (backend/api/bridge.py): /status and /healthz
answer while the service's event loop is busy; every other request still runs on the
service's loop. A real service (Zenoh on loopback, uvicorn on a free port)."""

from __future__ import annotations

import socket
import threading
import time

import httpx
import pytest

from backend.server import ServiceThread, bind_socket
from proto.transport import free_port
from backend.settings import ServiceSettings

BLOCK = 3.0  # s the test keeps the service's loop busy


@pytest.fixture
def svc(tmp_path):
    s = ServiceSettings.load(None, http={"host": "127.0.0.1", "port": 0},
                             zenoh={"listen": (f"tcp/127.0.0.1:{free_port()}",)}, state_dir=tmp_path, site="thread")
    with ServiceThread(s) as st:
        yield st


@pytest.mark.serial  # the answers are timed against the loop's busy spell
def test_status_answers_from_the_snapshot_while_the_loop_is_busy(svc):
    with httpx.Client(base_url=svc.url, timeout=30) as c:
        fresh = c.get("/status").json()
        assert time.time() - fresh["as_of"] < 5
        started = threading.Event()

        busy_from: list[float] = []

        def busy() -> None:  # the loop does synchronous work for BLOCK seconds
            busy_from.append(time.time())
            started.set()
            time.sleep(BLOCK)

        svc.loop.call_soon_threadsafe(busy)
        assert started.wait(10)
        t0 = time.monotonic()
        r = c.get("/status")
        took = time.monotonic() - t0
        assert r.status_code == 200 and took < BLOCK / 2, took
        snap = r.json()
        assert snap["as_of"] <= busy_from[0] and snap["site"] == "thread"  # published before, not computed now
        t0 = time.monotonic()
        assert c.get("/healthz").json()["ok"] and time.monotonic() - t0 < BLOCK / 2

        # any other request runs on the service's loop: it waits for it
        t0 = time.monotonic()
        assert c.get("/sessions").status_code == 200
        assert time.monotonic() - t0 > 0.5
        # the loop is free again: /status is fresh again
        again = c.get("/status").json()
        assert again["as_of"] > snap["as_of"] and time.time() - again["as_of"] < 2


def test_status_right_after_a_change_is_not_an_older_snapshot(svc):
    """After a session started or ended, /status waits for the loop rather than serve
    the snapshot from before: an operator's GET /status right after POST /sessions must
    show the session, however busy the loop."""
    with httpx.Client(base_url=svc.url, timeout=30) as c:
        assert c.get("/status").status_code == 200
        changed: list[float] = []
        started = threading.Event()

        def change_then_busy() -> None:  # what starting a session does, then a busy loop
            svc.service.active = svc.service.active
            changed.append(time.time())
            started.set()
            time.sleep(1.0)

        svc.loop.call_soon_threadsafe(change_then_busy)
        assert started.wait(10)
        snap = c.get("/status").json()
        assert snap["as_of"] >= changed[0]


def test_posts_and_event_streams_go_through_the_bridge(svc):
    with httpx.Client(base_url=svc.url, timeout=30) as c:
        r = c.post("/sessions", json={"intrinsics_yaml": "not: [valid"})
        assert r.status_code in (400, 422) and r.json()["detail"]  # the app's error mapping, unchanged
        with c.stream("GET", "/events") as ev:
            assert ev.status_code == 200
            lines = ev.iter_lines()
            assert next(lines).startswith("id: 0") and next(lines) == "event: hello"


def test_http_socket_is_tcp_so_responses_are_not_delayed():
    """A socket made with proto 0 is TCP, but asyncio only sets TCP_NODELAY on one that
    says IPPROTO_TCP: every response (headers, then body) then waited ~40 ms for the
    client's delayed ACK."""
    sock = bind_socket("127.0.0.1", 0)
    try:
        assert sock.proto == socket.IPPROTO_TCP
        client = socket.create_connection(sock.getsockname()[:2])
        sock.setblocking(True)
        conn, _ = sock.accept()
        with client, conn:
            assert conn.proto == socket.IPPROTO_TCP  # what asyncio checks before setting TCP_NODELAY
    finally:
        sock.close()
