"""The event fan-out behind GET /events (backend/events.py)."""

from __future__ import annotations

import asyncio

from backend.events import EventBus


def test_a_slow_subscriber_loses_its_oldest_events_counted_and_a_filter_keeps_its_kinds():
    async def main() -> None:
        bus = EventBus(maxlen=4)
        async with bus.subscribe() as every, bus.subscribe(frozenset({"calibration"})) as some:
            for k in range(10):
                bus.publish("cycle", {"cycle": k})
            bus.publish("calibration", {"version": 3})
            got = [every.get_nowait() for _ in range(every.qsize())]
            # the newest four kept, in order, and the seven pushed out counted
            assert [d.get("cycle", d.get("version")) for _, _, d in got] == [7, 8, 9, 3] and every.dropped == 7
            assert [i for i, _, _ in got] == [8, 9, 10, 11]  # ids go on across drops
            assert some.get_nowait() == (11, "calibration", {"version": 3}) and some.empty() and some.dropped == 0
            assert bus.subscribers == 2
        assert bus.subscribers == 0

    asyncio.run(main())


def test_close_ends_every_stream_also_a_full_one_and_later_subscribers_at_once():
    async def main() -> None:
        bus = EventBus(maxlen=2)
        async with bus.subscribe() as q:
            bus.publish("status", {"a": 1})
            bus.publish("status", {"a": 2})  # full
            bus.close()
            assert [q.get_nowait() for _ in range(q.qsize())][-1] is None
            bus.publish("status", {"a": 3})  # after close: nothing
            assert q.empty()
        async with bus.subscribe() as late:
            assert await asyncio.wait_for(late.get(), 1.0) is None

    asyncio.run(main())
