"""The solver process: GTSAM runs in a worker process so that the service's loop never
waits on it (gtsam holds Python's GIL while it optimises: a solve in a thread stalls the
loop for about as long as the solve, 0.32 s of a 0.37 s solve, measured). A
``ProcessPoolExecutor`` started with ``spawn`` takes a picklable ``optimize.Problem`` and
returns a ``Solution``."""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing
import signal
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import TYPE_CHECKING, Any, Callable

if TYPE_CHECKING:
    from .pipeline import Pipeline

SOLVER_NICE = 5  # the solver process's niceness above the service's (see _worker_init)


def _worker_init(parent: int) -> None:
    """The solver process leaves SIGINT/SIGTERM to the service: Ctrl-C in a terminal and
    systemd's stop signal reach the whole process group, and the cycle in flight must end
    (the service shuts the pool down itself). If the service dies (kill -9), nothing
    closes the pool's queue for us (the worker holds both ends), so a watchdog ends it."""
    import os
    import threading

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    # A solve can wait; ingest and /status cannot. When the cores are busy (overload, or a
    # small board running the detector too), the scheduler serves the service process first.
    try:
        os.nice(SOLVER_NICE)
    except OSError:  # a platform or a sandbox without nice: a slower /status, not a failure
        pass

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(0)

    threading.Thread(target=watch, name="parent-watchdog", daemon=True).start()


def warm_up() -> int:
    """Import the optimiser (and gtsam) in the worker before the first cycle needs it."""
    from . import optimize  # noqa: F401

    import os
    return os.getpid()


def finish_pipeline(pipeline: "Pipeline") -> "Pipeline":
    """Final batch adjustment, in the worker: it is a long GTSAM solve."""
    pipeline.finish()
    return pipeline


class SolverCrashed(RuntimeError):
    pass


class Solver:
    """One worker process for GTSAM; replaced if it dies."""

    def __init__(self, start_method: str = "spawn"):
        self._ctx = multiprocessing.get_context(start_method)
        self._pool: ProcessPoolExecutor | None = None
        self.restarts = 0
        self.busy = False

    def _ensure(self) -> ProcessPoolExecutor:
        if self._pool is None:
            import os

            self._pool = ProcessPoolExecutor(max_workers=1, mp_context=self._ctx, initializer=_worker_init,
                                             initargs=(os.getpid(),))
        return self._pool

    async def run(self, fn: Callable, *args: Any) -> Any:
        loop = asyncio.get_running_loop()
        pool = self._ensure()
        self.busy = True
        try:
            return await loop.run_in_executor(pool, fn, *args)
        except BrokenProcessPool as e:
            self.restarts += 1
            self._pool = None
            pool.shutdown(wait=False, cancel_futures=True)
            raise SolverCrashed(f"the solver process died ({e}); it was restarted") from None
        finally:
            self.busy = False

    def kill(self) -> None:
        """End the worker now, the job in flight with it (its ``run`` raises SolverCrashed):
        at shutdown, for a job that may take minutes (a live bootstrap) and is worth
        nothing after it. The pool has no public way to do this."""
        pool = self._pool
        for proc in list(getattr(pool, "_processes", {}).values()) if pool is not None else []:
            with contextlib.suppress(Exception):
                proc.kill()  # SIGKILL: the worker ignores SIGTERM (_worker_init)

    def shutdown(self) -> None:
        """Blocking: from a thread."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


def failed_solution(problem: Any, reason: str) -> Any:
    """A Solution that says the solve did not happen, so that apply() rejects the cycle
    (and the pipeline has no cycle in flight any more)."""
    from .optimize import failed

    return failed(problem, reason)
