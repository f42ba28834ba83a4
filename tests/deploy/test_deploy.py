"""deploy/: the compose file, the Dockerfile, the systemd unit and the example config are
consistent with each other and with the real `extrcal` command line."""

from __future__ import annotations

import configparser
import os
import re
import shlex
import shutil
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import pytest
import typer.main
import yaml
from typer.testing import CliRunner

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"


@pytest.fixture(scope="module")
def cli():
    from backend.cli import _register_all, app

    _register_all()
    return app


# Paths inside the image (Dockerfile) → the same files in the repository.
IMAGE_PATHS = {
    "/etc/extrcal/service.toml": str(DEPLOY / "service.toml"),
    "/etc/extrcal/lab": str(REPO / "edge_clients" / "data" / "ais_lab20"),
}


def _local(arg: str) -> str:
    for image, local in IMAGE_PATHS.items():
        if arg == image or arg.startswith(image + "/"):
            return local + arg[len(image):]
    return arg


def check_extrcal_argv(app, argv: list[str]) -> dict:
    """argv after `extrcal`: the real CLI parses it (subcommands, options, values, files),
    and `--help` of that command runs. Returns the parsed parameters."""
    cmd = typer.main.get_command(app)
    path = []
    args = [_local(a) for a in argv]
    while hasattr(cmd, "commands"):  # a group
        assert args, f"extrcal {' '.join(path)}: a subcommand is missing"
        sub = args.pop(0)
        assert sub in cmd.commands, f"extrcal {' '.join(path)}: no subcommand {sub!r}"
        path.append(sub)
        cmd = cmd.commands[sub]
    try:
        ctx = cmd.make_context(" ".join(["extrcal", *path]), args)
    except Exception as e:  # click's UsageError/BadParameter, from typer's copy of click
        pytest.fail(f"extrcal {' '.join(argv)}: {type(e).__name__}: {e}")
    r = CliRunner().invoke(app, [*path, "--help"])
    assert r.exit_code == 0, r.output
    return ctx.params


# ------------------------------------------------------------------ compose


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load((DEPLOY / "compose.yaml").read_text())


def _docker_compose_available() -> bool:
    if shutil.which("docker") is None:
        return False
    r = subprocess.run(["docker", "compose", "version"], capture_output=True, text=True, timeout=30)
    return r.returncode == 0


@pytest.mark.skipif(not _docker_compose_available(), reason="no docker CLI with the compose plugin here")
def test_docker_compose_config():
    env = {**os.environ, "EXTRCAL_TOKEN": "test-token"}
    r = subprocess.run(["docker", "compose", "-f", str(DEPLOY / "compose.yaml"), "config", "--quiet"],
                       capture_output=True, text=True, env=env, timeout=60)
    assert r.returncode == 0, r.stderr
    env.pop("EXTRCAL_TOKEN")
    r = subprocess.run(["docker", "compose", "-f", str(DEPLOY / "compose.yaml"), "config", "--quiet"],
                       capture_output=True, text=True, env=env, timeout=60)
    assert r.returncode != 0 and "EXTRCAL_TOKEN" in r.stderr


def test_compose_services(compose, cli):
    services = compose["services"]
    assert set(services) == {"router", "backend", "sensors"}
    # the router: zenohd of the same major protocol version as the Python package
    image, _, tag = services["router"]["image"].partition(":")
    assert image == "eclipse/zenoh" and tag, "pin the zenohd version"
    assert tag.split(".")[0] == version("eclipse-zenoh").split(".")[0]
    router_cmd = services["router"]["command"]
    listen = router_cmd[router_cmd.index("--listen") + 1]
    port = listen.rsplit(":", 1)[1]
    assert f"{port}:{port}" in services["router"]["ports"]

    backend = services["backend"]
    build = backend["build"]
    assert (DEPLOY / build["context"] / build["dockerfile"]).resolve() == (DEPLOY / "Dockerfile").resolve()
    assert services["sensors"]["image"] == backend["image"]
    for name in ("backend", "sensors"):
        argv = services[name]["command"]
        assert all(isinstance(a, str) for a in argv), f"{name}: quote numbers in the command"
        check_extrcal_argv(cli, argv)
        # everyone reaches the router by its service name and port
        connect = argv[argv.index("--zenoh-connect") + 1]
        assert connect == f"tcp/router:{port}"
    b = backend["command"]
    assert b[0] == "serve"
    http_port = b[b.index("--http") + 1].rsplit(":", 1)[1]
    assert f"{http_port}:{http_port}" in backend["ports"]
    # files the commands name are put in the image by the Dockerfile
    dockerfile = (DEPLOY / "Dockerfile").read_text()
    assert b[b.index("--config") + 1] == "/etc/extrcal/service.toml"
    assert re.search(r"^COPY deploy/service.toml /etc/extrcal/service.toml$", dockerfile, re.M)
    s = services["sensors"]["command"]
    assert s[:2] == ["sensor", "sim"]
    cams = s[s.index("--cameras") + 1]
    assert re.search(rf"^COPY edge_clients/data/ais_lab20 {re.escape(cams)}$", dockerfile, re.M)
    assert s[s.index("--site") + 1] == _service_toml()["site"]  # same key expressions
    # the state survives container restarts, the token is required
    assert any(v.endswith(":/var/lib/extrcal") for v in backend["volumes"])
    assert backend["environment"]["EXTRCAL_TOKEN"].startswith("${EXTRCAL_TOKEN:?")
    assert set(compose["volumes"]) == {v.split(":")[0] for v in backend["volumes"]}


# ------------------------------------------------------------------ Dockerfile


def test_dockerfile():
    text = (DEPLOY / "Dockerfile").read_text()
    lines = [ln.strip() for ln in re.sub(r"\\\n", " ", text).splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    froms = [ln.split()[1] for ln in lines if ln.startswith("FROM ")]
    assert froms and all(f == "python:3.11-slim" for f in froms)
    users = [ln.split()[1] for ln in lines if ln.startswith("USER ")]
    assert users and users[-1] not in ("root", "0"), "the image must run as a non-root user"
    final = lines[max(i for i, ln in enumerate(lines) if ln.startswith("FROM ")):]
    assert any(ln.startswith("USER ") for ln in final)
    assert any('pip wheel' in ln and '".[backend]"' in ln for ln in lines)
    assert 'ENTRYPOINT ["extrcal"]' in lines
    cmd = next(ln for ln in lines if ln.startswith("CMD "))
    assert cmd.startswith('CMD ["serve"')
    # every COPY source exists in the repository (build context = repository root)
    for ln in lines:
        if ln.startswith("COPY ") and "--from=" not in ln:
            for src in ln.split()[1:-1]:
                if src.endswith("*"):
                    continue  # optional files
                assert (REPO / src).exists(), f"Dockerfile copies {src}, which is not in the repository"
    # the RUN that makes the example initial estimate uses real flags
    perturb = next(ln for ln in lines if ln.startswith("RUN extrcal perturb"))
    from backend.cli import _register_all, app

    _register_all()
    argv = shlex.split(perturb)[2:]
    out = argv.index("--out") + 1
    argv[out] = str(REPO / "unused.yaml")  # written at build time; parsing does not write it
    check_extrcal_argv(app, argv)


def test_perturb_line_of_the_dockerfile_runs(tmp_path):
    """The build step that makes /etc/extrcal/lab/initial.yaml, run here on the lab files."""
    from backend.cli import _register_all, app

    _register_all()
    text = re.sub(r"\\\n", " ", (DEPLOY / "Dockerfile").read_text())
    line = next(ln.strip() for ln in text.splitlines() if ln.strip().startswith("RUN extrcal perturb"))
    argv = shlex.split(line)[2:]
    lab = REPO / "edge_clients" / "data" / "ais_lab20"
    argv = [a.replace("/etc/extrcal/lab", str(tmp_path)) for a in argv]
    shutil.copy(lab / "reference.yaml", tmp_path / "reference.yaml")
    r = CliRunner().invoke(app, argv)
    assert r.exit_code == 0, r.output
    from backend.cameras import load_extrinsics

    init = load_extrinsics(tmp_path / "initial.yaml")
    assert len(init) == 20


# ------------------------------------------------------------------ service.toml


def _service_toml() -> dict:
    import tomllib

    return tomllib.loads((DEPLOY / "service.toml").read_text())


def test_service_toml_loads_with_the_real_settings():
    from backend.settings import ServiceSettings, SettingsError

    with pytest.raises(SettingsError, match="without a token"):
        ServiceSettings.load(DEPLOY / "service.toml")
    s = ServiceSettings.load(DEPLOY / "service.toml", token="t0ken")
    assert str(s.state_dir) == "/var/lib/extrcal"
    assert s.http.host == "0.0.0.0" and s.http.port == 8000
    # the example camera files are the ones the image ships
    dockerfile = (DEPLOY / "Dockerfile").read_text()
    for name, path in s.camera_files.items():
        assert str(path).startswith("/etc/extrcal/lab/"), name
        fname = Path(path).name
        shipped = (REPO / "edge_clients" / "data" / "ais_lab20" / fname).is_file() or f"--out {path}" in dockerfile
        assert shipped, f"{path} is not in the image"


# ------------------------------------------------------------------ systemd


def _unit() -> configparser.ConfigParser:
    cp = configparser.ConfigParser(strict=False, interpolation=None, delimiters=("=",))
    cp.optionxform = str  # systemd keys are case-sensitive
    cp.read_string((DEPLOY / "extrcal.service").read_text())
    return cp


def test_systemd_unit_contents(cli):
    u = _unit()
    svc = u["Service"]
    argv = shlex.split(svc["ExecStart"])
    assert Path(argv[0]).name == "extrcal" and Path(argv[0]).is_absolute()
    assert argv[1] == "serve"
    check_extrcal_argv(cli, argv[1:])
    assert svc["Restart"] == "on-failure"
    assert svc["Type"] in ("exec", "simple")
    assert svc.get("DynamicUser") == "yes" or svc.get("User") not in (None, "root")
    assert svc["StateDirectory"] == "extrcal"
    state_dir = argv[argv.index("--state-dir") + 1]
    assert state_dir == "/var/lib/extrcal"
    for key in ("NoNewPrivileges", "ProtectSystem", "ProtectHome", "PrivateTmp", "CapabilityBoundingSet",
                "RestrictAddressFamilies", "SystemCallFilter"):
        assert key in svc, f"hardening option {key} missing"
    assert u["Install"]["WantedBy"] == "multi-user.target"


@pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                    reason="systemd-analyze is not installed (Debian package systemd)")
def test_systemd_analyze_verify(tmp_path):
    """systemd's own check. ExecStart must exist for it, so the unit is verified with the
    path of the extrcal installed here; it prints problems as warnings, hence no output."""
    exe = Path(sys.executable).parent / "extrcal"
    if not exe.exists():
        exe = Path(shutil.which("extrcal") or "/nonexistent")
    assert exe.exists(), "the extrcal command is not installed"
    text = (DEPLOY / "extrcal.service").read_text()
    argv0 = shlex.split(_unit()["Service"]["ExecStart"])[0]
    unit = tmp_path / "extrcal.service"
    unit.write_text(text.replace(argv0, str(exe)))
    r = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60,
                       env={**os.environ, "SYSTEMD_LOG_LEVEL": "warning"})
    assert r.returncode == 0 and not r.stderr.strip() and not r.stdout.strip(), r.stderr + r.stdout
    # and the check can fail: a typo is reported
    bad = tmp_path / "bad" / "extrcal.service"
    bad.parent.mkdir()
    bad.write_text(unit.read_text().replace("Restart=on-failure", "Restart=sometimes"))
    r = subprocess.run(["systemd-analyze", "verify", str(bad)], capture_output=True, text=True, timeout=60)
    assert "restart specifier" in r.stderr
