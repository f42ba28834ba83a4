"""The service's file writes (backend/writer.py): in order, in a thread, a failure counted
and reported while the writes after it still happen."""

from __future__ import annotations

import asyncio
import threading

from backend.writer import Writer


def test_writes_run_in_order_off_the_loop_and_a_failure_is_reported_not_raised():
    done: list[tuple[str, bool]] = []
    loop_thread = threading.get_ident()

    def write(name: str) -> None:
        done.append((name, threading.get_ident() != loop_thread))

    def full_disk(_: str) -> None:
        raise OSError(28, "No space left on device")

    async def main() -> Writer:
        w = Writer()
        task = asyncio.create_task(w.run())
        w.submit(write, "a")
        w.submit(full_disk, "b")
        assert len(w) == 2
        await w.flush()
        assert w.errors == 1 and w.writes == 1 and "No space left" in w.error
        w.submit(write, "c", storage=False)  # a publication says nothing about the disk
        await w.flush()
        assert w.error is not None
        w.submit(write, "d")
        await w.flush()
        w.close()
        await asyncio.wait_for(task, 5.0)
        return w

    w = asyncio.run(main())
    assert done == [("a", True), ("c", True), ("d", True)]
    assert w.error is None and w.writes == 2 and w.errors == 1
