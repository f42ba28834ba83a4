"""Hand-off from Zenoh threads, the service clock, per-sensor statistics."""

from __future__ import annotations

import asyncio
import threading
import time

import pytest

from backend.ingest import Arrival, HandOff, SensorStats, ServiceClock


class _Sample:
    def __init__(self, key: str, data: bytes):
        self.key_expr = key

        class P:
            def to_bytes(self_inner) -> bytes:
                return data

        self.payload = P()


def test_handoff_from_threads_is_bounded_and_counts_drops():
    async def main():
        loop = asyncio.get_running_loop()
        h = HandOff(loop, capacity=100)

        def produce(k: int) -> None:
            for i in range(250):
                h.on_sample(_Sample(f"extrcal/default/sensors/cam_{k}/keypoints", bytes([k, i % 256])))

        threads = [threading.Thread(target=produce, args=(k,)) for k in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        # let the loop run the scheduled hand-overs
        while h.received < 1000:
            await asyncio.sleep(0.001)
        assert len(h) == 100 and h.dropped == 900
        batch = await h.get_batch(1000)
        assert len(batch) == 100 and all(isinstance(a, Arrival) for a in batch)
        # the newest are kept: per producer, the last items it sent are among them
        assert max(a.wall for a in batch) <= time.time()
        h.close()
        assert await h.get_batch(10) == []

    asyncio.run(main())


def test_handoff_wakes_a_waiting_consumer():
    async def main():
        h = HandOff(asyncio.get_running_loop(), capacity=10)
        consumer = asyncio.create_task(h.get_batch(5))
        await asyncio.sleep(0.01)
        assert not consumer.done()
        threading.Thread(target=h.on_sample, args=(_Sample("k", b"x"),)).start()
        batch = await asyncio.wait_for(consumer, 30)
        assert [a.payload for a in batch] == [b"x"]

    asyncio.run(main())


class SteppedClock:
    """A monotonic clock the test advances by hand: no sleeps racing the scheduler."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_data_clock_follows_the_newest_stamp():
    mono = SteppedClock()
    c = ServiceClock("data", speed=10.0, grace=0.05, max_jump=5.0, monotonic=mono)
    assert c.now() is None
    assert c.observe(1000.0) == 1000.0
    assert c.observe(1000.5) == 1000.5 and c.now() == 1000.5
    # older stamps arrive at the clock's time (their latency is measured against it)
    assert c.observe(1000.2) == 1000.5
    # a stamp far ahead does not drag the clock
    assert c.observe(2000.0) == 1000.5 and c.now() == 1000.5
    # within the grace period it waits; beyond it the clock runs on at `speed`
    mono.t += 0.04
    assert c.now() == 1000.5
    mono.t += 0.11
    assert c.now() == pytest.approx(1000.5 + 10 * 0.1)


def test_wall_clock_is_the_host_clock():
    c = ServiceClock("wall")
    t = time.time()
    assert abs(c.now() - t) < 0.5 and abs(c.observe(1.0) - t) < 0.5


def test_sensor_stats_rate_latency_offset():
    s = SensorStats("cam_1")
    t0 = 1000.0
    for i in range(31):
        s.seen(t0 + i / 30)
        s.timing(t0 + i / 30 - 0.02 - 0.01 * (i % 3), t0 + i / 30, i)
    d = s.to_dict(t0 + 1.0)
    assert abs(d["rate"] - 30.0) < 0.5
    assert abs(d["latency"]["median"] - 0.03) < 1e-9 and abs(d["latency"]["max"] - 0.04) < 1e-9
    assert abs(d["clock_offset"] - 0.02) < 1e-9
    assert s.to_dict(t0 + 60)["rate"] == 0.0  # went quiet


def test_data_clock_never_runs_ahead_of_slow_data_nor_back():
    # data comes at 1 data-s per 0.03 wall-s (10x), the clock's run-on speed is 100x:
    # as long as messages flow, the clock is the newest stamp, not an extrapolation
    mono = SteppedClock()
    c = ServiceClock("data", speed=100.0, grace=0.05, max_jump=5.0, monotonic=mono)
    stamp = 1000.0
    for _ in range(5):
        c.observe(stamp)
        mono.t += 0.03
        assert c.now() == stamp
        stamp += 0.3
    # silence: it runs on; when data resumes behind it, it does not step back
    mono.t += 0.2
    ran_on = c.now()
    assert ran_on == pytest.approx(stamp - 0.3 + 100 * (0.23 - 0.05))
    assert c.observe(stamp) == ran_on and c.now() == ran_on
    mono.t += 0.01  # data flows again: no run-on within the grace period
    assert c.now() == ran_on


def test_data_clock_follows_the_typical_sensor_not_one_whose_clock_jumped():
    c = ServiceClock("data", max_jump=5.0)
    for k in range(10):
        for s in ("cam_0", "cam_1", "cam_2"):
            c.observe(1000.0 + 0.1 * k, s)
    c.observe(1002.9, "cam_3")  # 2 s ahead: must not move the clock for the others
    assert c.now() == pytest.approx(1000.9)
    for s in ("cam_0", "cam_1", "cam_2"):
        c.observe(1001.0, s)
    assert c.now() == pytest.approx(1001.0)


def test_data_clock_follows_when_most_sensors_are_far_ahead():
    """Under overload with data 10x faster than real time, a loop stall of half a second
    while the hand-off drops the oldest makes every sensor's next stamp > max_jump ahead:
    the clock must follow (it froze, and every message was `stamp_in_future`), while one
    sensor far ahead still does not drag it."""
    c = ServiceClock("data", speed=1.0, grace=60.0, max_jump=5.0)
    for k in range(5):
        c.observe(1000.0, f"s{k}")
    assert c.observe(1100.0, "s0") == 1000.0  # one sensor's clock jumped: ignored
    assert c.observe(1020.0, "s1") == 1000.0  # two of five ahead: not yet
    assert c.observe(1020.0, "s2") == 1020.0  # most are ahead: the clock was behind
    assert c.observe(1020.5, "s3") == 1020.0 and c.now() == 1020.0


def test_handoff_refuses_sensors_outside_the_session_on_the_zenoh_thread():
    async def main():
        h = HandOff(asyncio.get_running_loop(), capacity=10)
        h.accept(frozenset({"cam_1"}))

        def produce() -> None:
            for i in range(50):
                h.on_sample(_Sample("extrcal/default/sensors/intruder/keypoints", b"junk"))
                h.on_sample(_Sample(f"extrcal/default/sensors/other_{i}/keypoints", b"junk"))
            h.on_sample(_Sample("extrcal/default/sensors/cam_1/keypoints", b"good"))

        t = threading.Thread(target=produce)
        t.start()
        t.join()
        batch = await asyncio.wait_for(h.get_batch(100), 30)
        assert [a.payload for a in batch] == [b"good"]  # only the session's sensor was queued
        assert h.received == 1 and h.dropped == 0 and h.refused == 100
        refused = h.take_refused()
        assert refused["intruder"].count == 50 and sum(r.count for r in refused.values()) == 100
        assert refused["intruder"].first_wall <= refused["intruder"].last_wall
        assert h.take_refused() == {}  # taken once
        h.accept(None)  # no session: everything is queued (and counted on the loop)
        h.on_sample(_Sample("extrcal/default/sensors/intruder/keypoints", b"x"))
        assert len(h) == 1 and h.refused == 100
        # one wake-up per batch, not per message: the consumer was not waiting
        assert h.wakeups <= 2

    asyncio.run(main())
