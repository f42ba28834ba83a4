"""Zenoh session settings shared by the backend and every edge client.

Every command that talks Zenoh takes the same flags (--zenoh-listen, --zenoh-connect,
--zenoh-mode, --site); this turns them into a zenoh.Config. Multicast scouting is off
by default: sensors find the backend (or a router) through explicit endpoints.
"""

from __future__ import annotations

import json
import random
import socket
from dataclasses import dataclass
from pathlib import Path

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"


@dataclass(frozen=True)
class ZenohSettings:
    mode: str = "peer"  # peer | client | router
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    config_file: str | None = None  # a full Zenoh JSON5 config (TLS, ACL...); flags override it

    def to_config(self):
        import zenoh

        if self.config_file:
            if not Path(self.config_file).is_file():
                raise FileNotFoundError(f"Zenoh config file {self.config_file} does not exist")
            cfg = zenoh.Config.from_file(self.config_file)
        else:
            cfg = zenoh.Config()
        if self.mode not in ("peer", "client", "router"):
            raise ValueError(f"Zenoh mode must be peer, client or router, got {self.mode!r}")
        cfg.insert_json5("mode", json.dumps(self.mode))
        if not self.config_file or not self.multicast_scouting:
            cfg.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        if self.listen:
            cfg.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        if self.connect:
            cfg.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        return cfg


def open_session(settings: ZenohSettings):
    """Blocking: call from a thread (asyncio.to_thread) inside async code."""
    import zenoh

    return zenoh.open(settings.to_config())


def _ephemeral_low() -> int:
    """The lowest port the kernel gives outgoing connections (Linux; else IANA's)."""
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
            return int(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        return 49152


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (for Zenoh endpoints in tests and
    the demo), below the kernel's ephemeral range when there is room: a port the kernel hands
    out for bind(0) is one any outgoing connection may take before the listener binds it
    (seen in CI: a Zenoh TLS listener's "address already in use")."""
    lo = _ephemeral_low()
    if lo - 1024 >= 4096:
        for _ in range(100):
            port = random.randrange(max(1024, lo - 16384), lo)
            with socket.socket() as s:
                try:
                    s.bind(("127.0.0.1", port))
                except OSError:
                    continue
                return port
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
