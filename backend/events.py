"""Progress events for the event stream (``GET /events``): a fan-out with a bounded queue
per subscriber."""

from __future__ import annotations

import asyncio
import contextlib
from typing import Any, AsyncIterator


class EventBus:
    """Fan-out of progress events to server-sent-event clients.

    Each subscriber has a bounded queue; a slow client loses its oldest events (and is
    told how many in the next event's ``dropped``) instead of growing memory.
    """

    KINDS = frozenset({"status", "cycle", "session", "service", "camera_moved", "camera_restarted", "calibration",
                       "hypotheses"})  # what ``publish`` is called with (and ``hello``, first on every stream)

    def __init__(self, maxlen: int = 256):
        self._subs: dict[asyncio.Queue, frozenset[str] | None] = {}  # queue -> the kinds it takes (None: all)
        self._maxlen = maxlen
        self._id = 0
        self.closed = False

    def publish(self, kind: str, data: dict[str, Any]) -> None:
        if self.closed:
            return
        self._id += 1
        item = (self._id, kind, data)
        for q, kinds in self._subs.items():
            if kinds is not None and kind not in kinds:
                continue
            if q.full():
                q.get_nowait()
                q.dropped += 1  # type: ignore[attr-defined]
            q.put_nowait(item)

    @contextlib.asynccontextmanager
    async def subscribe(self, kinds: frozenset[str] | None = None) -> AsyncIterator[asyncio.Queue]:
        """A queue of the events published from now on; ``kinds``: only these (a client
        that waits for alarms must not lose one to a flood of ``cycle`` and ``hypotheses``)."""
        assert kinds is None or kinds <= self.KINDS, kinds
        q: asyncio.Queue = asyncio.Queue(self._maxlen)
        q.dropped = 0  # type: ignore[attr-defined]
        if self.closed:
            q.put_nowait(None)
        self._subs[q] = kinds
        try:
            yield q
        finally:
            self._subs.pop(q, None)

    def close(self) -> None:
        """End every stream (the server can then shut down without waiting on them)."""
        self.closed = True
        for q in self._subs:
            if q.full():
                q.get_nowait()
            q.put_nowait(None)

    @property
    def subscribers(self) -> int:
        return len(self._subs)
