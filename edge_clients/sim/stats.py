"""What a simulated run contained, as figures and a table."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SimStats:
    messages: dict[str, int]

    def table(self) -> str:
        raise NotImplementedError("work in progress")
