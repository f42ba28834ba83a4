"""Zenoh key expressions (shared/FORMATS.md)."""

from __future__ import annotations

DEFAULT_SITE = "default"
_BAD = set("/*$?#")


def _check(name: str, what: str) -> str:
    if not name or set(name) & _BAD:
        raise ValueError(f"{what} {name!r} must be non-empty and contain none of / * $ ? #")
    return name


def keypoints(site: str, sensor: str) -> str:
    return f"extrcal/{_check(site, 'site')}/sensors/{_check(sensor, 'sensor')}/keypoints"


def all_keypoints(site: str) -> str:
    return f"extrcal/{_check(site, 'site')}/sensors/*/keypoints"


def calibration(site: str) -> str:
    return f"extrcal/{_check(site, 'site')}/calibration"


def alive(site: str, sensor: str) -> str:
    return f"extrcal/{_check(site, 'site')}/sensors/{_check(sensor, 'sensor')}/alive"


def all_alive(site: str) -> str:
    return f"extrcal/{_check(site, 'site')}/sensors/*/alive"


def sensor_of(key: str) -> str | None:
    """The sensor id in a keypoints or alive key, else None."""
    parts = str(key).split("/")
    if len(parts) == 5 and parts[0] == "extrcal" and parts[2] == "sensors":
        return parts[3]
    return None
