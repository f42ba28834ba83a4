"""The calibration pipeline: every stage wired top to bottom, driven by a clock.

    message ─► ingest (validate against the camera set, clock checks)
            ─► sync        framesets of per-sensor messages close in time
            ─► preprocess  filters, undistortion
            ─► associate   person hypotheses across views
            ─► queue       bounded, newest kept
            ─► select      one cycle's hypotheses (every `select.interval` s of data time)
            ─► optimize    GTSAM factor graph → poses + marginals   (pure function, any process)
            ─► refine      Kalman update on SE(3), scale kept from the initial estimate
            ─► state       CalibrationState

The clock is the caller's: offline it is the recording's data time, live it is the
wall clock. ``run_offline`` drives it synchronously; the service drives ``advance`` on
its event loop and ``optimize.solve`` in a worker process.
"""

from __future__ import annotations

# IMPLEMENTATION IN PROGRESS: the public surface below is the contract the service
# builds against.
#
# class Pipeline:
#     def __init__(self, cameras: CameraSet, config: EngineConfig, *, seed: int = 0): ...
#     def push(self, msg: KeypointMessage, arrival: float) -> str | None:
#         """Take one validated message; returns the rejection reason or None."""
#     def advance(self, now: float) -> None:
#         """Run sync/preprocess/associate up to clock time `now` (data time)."""
#     def next_problem(self, now: float) -> optimize.Problem | None:
#         """A cycle's problem when one is due (interval elapsed, enough hypotheses), else None.
#         Problem is plain arrays and picklable; solve it with optimize.solve anywhere."""
#     def apply(self, problem, solution) -> CycleReport: ...
#     def state(self) -> CalibrationState: ...
#     def finish(self) -> CalibrationState:
#         """Final batch adjustment over the kept hypotheses (if configured)."""
#     def snapshot(self) -> dict: ...            # JSON-able, for persistence
#     @classmethod
#     def restore(cls, cameras, config, snapshot: dict) -> "Pipeline": ...
#
# def run_offline(cameras, config, messages: Iterable[KeypointMessage], *, seed=0,
#                 progress: Callable[[CalibrationState], None] | None = None) -> CalibrationState
