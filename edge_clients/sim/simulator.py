"""The simulator: walkers in a scene seen by free-running, imperfect sensors."""

from __future__ import annotations

import os
from typing import Iterable, Iterator

from proto import KeypointMessage

from .config import SimConfig
from .scene import Scene
from .stats import SimStats
from .truth import Truth


class Simulator:
    def __init__(self, scene: Scene, config: SimConfig = SimConfig()):
        self.scene = scene
        self.config = config

    def messages(self, sensors: Iterable[str] | None = None) -> Iterator[tuple[float, KeypointMessage]]:
        """(arrival epoch s, message) in arrival order; never precomputes the whole run."""
        raise NotImplementedError("work in progress")

    @property
    def truth(self) -> Truth:
        raise NotImplementedError("work in progress")

    def write(self, out_path: str | os.PathLike) -> SimStats:
        raise NotImplementedError("work in progress")
