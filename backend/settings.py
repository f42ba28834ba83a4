"""Settings of the live service (`extrcal serve`): TOML file, EXTRCAL_* variables, flags.

Precedence, highest first: command-line flags, environment variables (``EXTRCAL_SITE``,
``EXTRCAL_HTTP__PORT``, ``EXTRCAL_ZENOH__LISTEN='["tcp/0.0.0.0:7447"]'``...), the TOML
file given with ``--config``, the defaults below. Unknown keys are errors, so a typo in
a config file is reported instead of silently ignored.

Example service.toml::

    site = "lab"
    state_dir = "/var/lib/extrcal"
    token = "change-me"            # needed for POST endpoints; required off loopback
    clock = "wall"                 # sensors are NTP-synchronised
    engine_config = "engine.toml"  # EngineConfig sections (sync, preprocess, ...)

    [http]
    host = "0.0.0.0"
    port = 8000

    [zenoh]
    mode = "peer"
    listen = ["tcp/0.0.0.0:7447"]

    [camera_files]                 # files sessions may name instead of uploading
    lab_intrinsics = "/etc/extrcal/intrinsics.yaml"
    lab_initial = "/etc/extrcal/initial.yaml"

    [defaults]                     # used when a session names no file
    intrinsics = "lab_intrinsics"
    initial = "lab_initial"
"""

from __future__ import annotations

import ipaddress
import tomllib
from contextvars import ContextVar
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, SecretStr, ValidationError, field_validator, model_validator
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict

from proto.keys import DEFAULT_SITE, _check as _check_key_part
from proto.transport import DEFAULT_LISTEN, ZenohSettings

_toml_path: ContextVar[Path | None] = ContextVar("extrcal_service_toml", default=None)


class SettingsError(ValueError):
    """Settings that cannot work; the message names the source and the field."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class HttpSettings(_Model):
    host: str = Field("127.0.0.1", description="address the REST API listens on")
    port: int = Field(8000, ge=0, le=65535, description="0 picks a free port")


class ZenohOptions(_Model):
    mode: Literal["peer", "client", "router"] = "peer"
    listen: tuple[str, ...] | None = Field(
        None, description=f"endpoints to listen on (default: {DEFAULT_LISTEN} for a peer or router, none for a client)")
    connect: tuple[str, ...] = Field((), description="endpoints (routers, peers) to connect to")
    multicast_scouting: bool = Field(False, description="off: sensors find the backend through explicit endpoints")
    config_file: Path | None = Field(None, description="a full Zenoh JSON5 config (TLS, access control); the fields above override it")

    @model_validator(mode="before")
    @classmethod
    def _default_listen(cls, data: Any) -> Any:
        if isinstance(data, dict) and data.get("listen") is None:
            data = {**data, "listen": () if data.get("mode") == "client" else (DEFAULT_LISTEN,)}
        return data

    def transport(self) -> ZenohSettings:
        return ZenohSettings(
            mode=self.mode, listen=tuple(self.listen), connect=tuple(self.connect),
            multicast_scouting=self.multicast_scouting,
            config_file=str(self.config_file) if self.config_file else None,
        )


class CameraDefaults(_Model):
    intrinsics: str | None = Field(None, description="name in camera_files used when a session names no intrinsics")
    initial: str | None = None
    reference: str | None = None


class ServiceSettings(BaseSettings):
    """Everything `extrcal serve` needs; see the module docstring for the sources."""

    model_config = SettingsConfigDict(
        env_prefix="EXTRCAL_", env_nested_delimiter="__", extra="forbid", frozen=True,
    )

    site: str = Field(DEFAULT_SITE, description="<site> in the Zenoh key expressions")
    http: HttpSettings = HttpSettings()
    zenoh: ZenohOptions = Field(default_factory=lambda: ZenohOptions.model_validate({}))
    state_dir: Path = Field(Path("extrcal-state"), description="sessions, results, history, snapshots")
    token: SecretStr | None = Field(None, description="bearer token for state-changing endpoints")
    protect_reads: bool = Field(False, description="require the token for read endpoints too")
    clock: Literal["wall", "data"] = Field(
        "wall",
        description="'wall': the pipeline's clock is this host's clock (NTP-synchronised sensors); "
        "'data': it follows the newest message stamp (replays, simulations, sped-up demos)",
    )
    speed: float = Field(1.0, gt=0, le=1000, description="data seconds per wall second when the data clock runs without data")
    engine_config: Path | None = Field(None, description="TOML with EngineConfig sections, the base of every session")
    camera_files: dict[str, Path] = Field(default_factory=dict, description="camera files sessions may name")
    defaults: CameraDefaults = CameraDefaults()
    ingest_queue: int = Field(20000, ge=10, description="messages waiting for the loop; the oldest are dropped beyond")
    snapshot_interval: float = Field(0.0, ge=0, description="s of wall time between pipeline snapshots (0: after every cycle)")
    tick: float = Field(0.02, gt=0, le=1, description="s between front-end advances on the loop")
    solver_start: Literal["spawn", "forkserver"] = Field("spawn", description="how the solver process starts")

    @field_validator("site")
    @classmethod
    def _site(cls, v: str) -> str:
        _check_key_part(v, "site")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> "ServiceSettings":
        for what, name in self.defaults.model_dump().items():
            if name is not None and name not in self.camera_files:
                raise ValueError(f"defaults.{what} = {name!r} is not a key of camera_files")
        if self.token is not None and not self.token.get_secret_value().strip():
            raise ValueError("token must not be empty")
        if not is_loopback(self.http.host) and self.token is None:
            raise ValueError(
                f"refusing to listen on {self.http.host} (not loopback) without a token: "
                "set token (--token, EXTRCAL_TOKEN) or listen on 127.0.0.1"
            )
        return self

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        return (init_settings, env_settings, _TomlSource(settings_cls))

    @staticmethod
    def load(config: str | Path | None = None, **overrides: Any) -> "ServiceSettings":
        """Settings from a TOML file (optional), the environment and ``overrides`` (flags).

        ``overrides`` are nested like the TOML (``http={"port": 9000}``); None means "not
        given". Nested sections merge across sources. Raises SettingsError naming the
        source and the field.
        """
        path = Path(config).expanduser() if config is not None else None
        if path is not None and not path.is_file():
            raise SettingsError(f"{path}: service config file does not exist")
        token = _toml_path.set(path)
        try:
            return ServiceSettings(**_drop_none(overrides))
        except ValidationError as e:
            raise SettingsError(f"{path or 'settings'}: {_describe(e)}") from None
        finally:
            _toml_path.reset(token)

    def token_value(self) -> str | None:
        return self.token.get_secret_value() if self.token is not None else None


class _TomlSource(PydanticBaseSettingsSource):
    """The TOML file named by ``ServiceSettings.load`` (lowest priority but defaults)."""

    @staticmethod
    def read(path: Path) -> dict[str, Any]:
        try:
            d = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as e:
            raise SettingsError(f"{path}: not valid TOML: {e}") from None
        except OSError as e:
            raise SettingsError(f"{path}: cannot read: {e}") from None
        # Paths in the file are relative to the file, not to the working directory.
        for key in ("state_dir", "engine_config"):
            if isinstance(d.get(key), str):
                d[key] = str(_relative_to(path, d[key]))
        if isinstance(d.get("camera_files"), dict):
            d["camera_files"] = {k: str(_relative_to(path, v)) if isinstance(v, str) else v
                                 for k, v in d["camera_files"].items()}
        z = d.get("zenoh")
        if isinstance(z, dict) and isinstance(z.get("config_file"), str):
            z["config_file"] = str(_relative_to(path, z["config_file"]))
        return d

    def get_field_value(self, field, field_name):  # pragma: no cover - __call__ is used
        return None, field_name, False

    def __call__(self) -> dict[str, Any]:
        path = _toml_path.get()
        return self.read(path) if path is not None else {}


def _relative_to(config: Path, value: str) -> Path:
    p = Path(value).expanduser()
    return p if p.is_absolute() else (config.parent / p)


def _drop_none(d: dict[str, Any]) -> dict[str, Any]:
    """Flags that were not given are None; nested sections merge with the other sources."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            v = _drop_none(v)
            if not v:
                continue
        if v is not None:
            out[k] = v
    return out


def is_loopback(host: str) -> bool:
    if host in ("localhost", "ip6-localhost"):
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def parse_hostport(value: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:8000`` for IPv6, ``:8000`` for the default host)."""
    host, sep, port = value.rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise SettingsError(f"--http: expected HOST:PORT, got {value!r}")
    return (host.strip("[]") or "127.0.0.1"), int(port)


def _describe(e: ValidationError) -> str:
    parts = []
    for err in e.errors():
        loc = ".".join(str(x) for x in err["loc"])
        msg = err["msg"].removeprefix("Value error, ")
        parts.append(f"{loc}: {msg}" if loc else msg)
    return "; ".join(parts)
