"""The service's file writes (results, snapshots, records, versions): in order, one at a
time, in a thread, so that the loop never waits on the disk."""

from __future__ import annotations

import asyncio
import logging
from typing import Any, Callable

log = logging.getLogger("extrcal.service")  # the service's: its messages keep their logger


class Writer:
    """File writes in order, one at a time, in a thread; failures are reported, not raised."""

    def __init__(self) -> None:
        self._q: asyncio.Queue = asyncio.Queue()
        self.error: str | None = None
        self.errors = 0
        self.writes = 0

    def submit(self, fn: Callable, *args: Any, storage: bool = True) -> None:
        """``storage``: a write to the state directory, whose success clears ``error``
        (a Zenoh publication through this queue says nothing about the disk)."""
        self._q.put_nowait((fn, args, storage))

    async def run(self) -> None:
        while True:
            item = await self._q.get()
            try:
                if item is None:
                    return
                fn, args, storage = item
                try:
                    await asyncio.to_thread(fn, *args)
                    if storage:
                        self.writes += 1
                        self.error = None
                except (OSError, ValueError) as e:
                    self.errors += 1
                    self.error = f"{type(e).__name__}: {e}"
                    log.error("state directory write failed: %s", self.error)
                except Exception as e:  # a bug in one write must not stop the others
                    self.errors += 1
                    self.error = f"{type(e).__name__}: {e}"
                    log.exception("writer task failed")
            finally:
                self._q.task_done()

    async def flush(self) -> None:
        await self._q.join()

    def close(self) -> None:
        self._q.put_nowait(None)

    def __len__(self) -> int:
        return self._q.qsize()
