"""Service settings: TOML file < EXTRCAL_* variables < flags; clear errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from backend.settings import ServiceSettings, SettingsError, is_loopback, parse_hostport


def _toml(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "service.toml"
    p.write_text(text)
    return p


def test_defaults_are_loopback_peer_without_multicast(monkeypatch):
    for k in list(__import__("os").environ):
        if k.startswith("EXTRCAL_"):
            monkeypatch.delenv(k)
    s = ServiceSettings.load()
    assert (s.http.host, s.http.port) == ("127.0.0.1", 8000)
    z = s.zenoh.transport()
    assert z.mode == "peer" and z.listen == ("tcp/127.0.0.1:7447",) and not z.multicast_scouting
    assert s.site == "default" and s.token is None and s.clock == "wall"


def test_precedence_flags_over_env_over_file(tmp_path, monkeypatch):
    cfg = _toml(tmp_path, """
site = "file"
state_dir = "state"
[http]
port = 9001
host = "127.0.0.1"
[zenoh]
listen = ["tcp/127.0.0.1:7500"]
[camera_files]
lab = "cams/intrinsics.yaml"
[defaults]
intrinsics = "lab"
""")
    monkeypatch.setenv("EXTRCAL_SITE", "env")
    monkeypatch.setenv("EXTRCAL_HTTP__PORT", "9002")
    s = ServiceSettings.load(cfg)
    assert s.site == "env" and s.http.port == 9002 and s.http.host == "127.0.0.1"
    assert s.zenoh.listen == ("tcp/127.0.0.1:7500",)
    # paths in the file are relative to the file
    assert s.state_dir == tmp_path / "state"
    assert s.camera_files["lab"] == tmp_path / "cams" / "intrinsics.yaml"
    s = ServiceSettings.load(cfg, site="flag", http={"port": 9003, "host": None}, zenoh={"listen": None})
    assert s.site == "flag" and s.http.port == 9003 and s.zenoh.listen == ("tcp/127.0.0.1:7500",)


@pytest.mark.parametrize("text, needle", [
    ("bogus = 1", "bogus"),
    ("[http]\nport = 'x'", "http.port"),
    ("[zenoh]\nmode = 'satellite'", "zenoh.mode"),
    ("site = 'a/b'", "site"),
    ("[defaults]\nintrinsics = 'nowhere'", "camera_files"),
    ("this is = not toml =", "not valid TOML"),
])
def test_bad_files_name_the_field(tmp_path, text, needle):
    with pytest.raises(SettingsError, match=needle) as e:
        ServiceSettings.load(_toml(tmp_path, text))
    assert str(tmp_path / "service.toml") in str(e.value)


def test_missing_file():
    with pytest.raises(SettingsError, match="does not exist"):
        ServiceSettings.load("/nonexistent/service.toml")


def test_refuses_public_address_without_token():
    with pytest.raises(SettingsError, match="without a token"):
        ServiceSettings.load(http={"host": "0.0.0.0"})
    s = ServiceSettings.load(http={"host": "0.0.0.0"}, token="s3cret")
    assert s.token_value() == "s3cret"
    assert "s3cret" not in repr(s)  # a secret stays out of logs
    with pytest.raises(SettingsError, match="token"):
        ServiceSettings.load(token="  ")


def test_hostport_and_loopback():
    assert parse_hostport("0.0.0.0:80") == ("0.0.0.0", 80)
    assert parse_hostport("[::1]:8000") == ("::1", 8000)
    assert parse_hostport(":8000") == ("127.0.0.1", 8000)
    for bad in ("8000", "host:", "host:99999", "h:p"):
        with pytest.raises(SettingsError):
            parse_hostport(bad)
    assert is_loopback("127.0.0.2") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.2") and not is_loopback("example.org")


def test_serve_command_refuses_bad_addresses():
    """`extrcal serve` says what is wrong in one line and exits 2, before opening anything."""
    import socket

    from typer.testing import CliRunner

    from backend.cli import _register_all, app

    _register_all()
    r = CliRunner().invoke(app, ["serve", "--http", "0.0.0.0:0"])
    assert r.exit_code == 2 and "without a token" in r.output
    r = CliRunner().invoke(app, ["serve", "--http", "localhost"])
    assert r.exit_code == 2 and "HOST:PORT" in r.output
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        r = CliRunner().invoke(app, ["serve", "--http", f"127.0.0.1:{port}", "--state-dir", "/nonexistent-extrcal"])
        assert r.exit_code == 2 and f"cannot listen on 127.0.0.1:{port}" in r.output


def test_a_zenoh_client_listens_nowhere_by_default():
    s = ServiceSettings.load(zenoh={"mode": "client", "connect": ("tcp/127.0.0.1:7447",)})
    assert s.zenoh.listen == () and s.zenoh.transport().connect == ("tcp/127.0.0.1:7447",)
    assert ServiceSettings.load(zenoh={"mode": "router"}).zenoh.listen == ("tcp/127.0.0.1:7447",)
