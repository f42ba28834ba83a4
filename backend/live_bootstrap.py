"""A live session without an initial estimate: collect, bootstrap, hand over, calibrate.

The online pipeline needs a start (its association cuts rays to depth intervals in a
known world); offline, ``extrcal calibrate`` bootstraps one from the first
``bootstrap.max_seconds`` of a recording (backend/bootstrap.py). Live there is no
recording: the session collects the data first.

    POST /sessions without an initial estimate (or with distrust_initial)
      │
      ▼ collecting    ``Collector`` stands in for the pipeline: the pipeline's own sync and
      │               preprocess, framesets archived, no association, no cycles (no poses)
      │ every ``live_interval`` s of data from ``live_first`` on: a ``BootstrapJob`` (a
      │ frozen copy of the frames) runs ``bootstrap`` in the solver process (GTSAM holds
      │ the GIL for seconds: not in a thread of the loop's process)
      ▼ bootstrapping accepted (``Collector.conclude``) when it placed ``live_min_placed`` of
      │               the cameras that saw people, or any result from ``max_seconds`` on;
      │               else (or when it failed: too few pairs) the next attempt has more data
      ▼ handover      ``Handover.build`` (in a thread): the online ``Pipeline`` from the
      │               result (``bootstrap.handover``: the floor's frame, the people's scale,
      │               an honest std), or with an initial estimate the data's shape aligned
      │               onto it (``reconcile``, as ``extrcal calibrate``); every frame
      │               collected so far is associated and queued (``Pipeline.take_frames``)
      ▼ calibrating   the service swaps the pipeline in and goes on live

Cameras the bootstrap did not place are not in the online pipeline (as offline: a camera
without a pose would only feed wrong associations); their framesets are archived beside it
and they are resected while the session runs (``bootstrap.late_join_interval``: one that
passes joins the running pipeline) and when it stops, joining its final batch when they
pass (backend/late_join.py, ``late_record``); the session lists them as not placed until then.

Everything here is synchronous and free of asyncio: the service (backend/service.py)
drives it from its loop.
"""

from __future__ import annotations

import math
import time as _time
from collections import Counter, deque
from dataclasses import dataclass, field, replace
from typing import Any, Mapping, Sequence

import numpy as np

from proto import KeypointMessage

from .bootstrap import (
    BootstrapError, BootstrapResult, Frame, bootstrap, camera_set, handover, mistimed_summary, stamps_apart,
)
from .cameras import CameraSet, dump_extrinsics
from .config import EngineConfig
from .preprocess import Preprocessor
from .stamp_watch import StampWatch
from .state import CalibrationState, Counters
from .sync import Synchronizer


@dataclass(frozen=True)
class LiveOptions:
    """What a bootstrapping session was asked: ``heights`` (m) of the walkers, if known
    (else the population prior sets the scale); ``distrust_initial``: bootstrap although
    an initial estimate was given, then reconcile the two (its frame and scale kept)."""

    heights: tuple[float, ...] = ()
    distrust_initial: bool = False

    def to_dict(self) -> dict[str, Any]:
        return {"person_height": list(self.heights) or None, "distrust_initial": self.distrust_initial}

    @staticmethod
    def from_dict(d: dict[str, Any] | None) -> "LiveOptions":
        d = d or {}
        return LiveOptions(tuple(float(h) for h in d.get("person_height") or ()), bool(d.get("distrust_initial")))


@dataclass(frozen=True, eq=False)
class BootstrapJob:
    """One attempt: a frozen copy of the collected frames and what ``bootstrap`` needs;
    picklable (it runs in the solver process). ``seen`` (C,) int: framesets in which each
    camera had a detection (the acceptance rule's denominator); ``final``: at or beyond
    the deadline, any result that places cameras is taken."""

    attempt: int
    frames: tuple[Frame, ...]
    names: tuple[str, ...]
    focal: np.ndarray
    config: EngineConfig
    heights: tuple[float, ...]
    seed: int
    data_seconds: float
    seen: np.ndarray
    final: bool
    mistimed: Mapping[str, float] = field(default_factory=dict)  # to be timed: ``bootstrap.stamps_apart``

    def __post_init__(self) -> None:
        assert self.focal.shape == (len(self.names),) and self.seen.shape == (len(self.names),)


def seen_per_camera(frames: Sequence[Frame], cameras: int) -> np.ndarray:
    """(C,) int: the framesets in which each camera has a detection (``BootstrapJob.seen``)."""
    seen = np.zeros(cameras, dtype=np.int64)
    for _, views in frames:
        for v in views:
            if v:  # a camera's view, with its detections
                seen[v[0].cam] += 1
    return seen


@dataclass(frozen=True, eq=False)
class Outcome:
    """What an attempt gave: the result, or why there is none; its wall seconds."""

    result: BootstrapResult | None
    error: str | None
    seconds: float


def run_job(job: BootstrapJob) -> Outcome:
    """The bootstrap of one job (in the solver process: module level, picklable). A
    BootstrapError (too few pairs, too few persons) is an outcome, not an exception."""
    t0 = _time.perf_counter()
    try:
        res = bootstrap(job.frames, job.names, job.focal, job.config, heights=job.heights, seed=job.seed,
                        mistimed=job.mistimed)
    except BootstrapError as e:
        return Outcome(None, str(e), _time.perf_counter() - t0)
    return Outcome(res, None, _time.perf_counter() - t0)


@dataclass(frozen=True, eq=False)
class Handover:
    """The online pipeline built from an accepted bootstrap, ready to swap in.

    ``cameras``: the camera set it runs on (the placed cameras, or the initial estimate's);
    ``initial_yaml``: that set's poses as the session's initial estimate (None when the
    session had one and keeps it); ``config``: the effective engine config; ``taken``:
    the last frameset time fed to it; ``meta``: frame, scale, placed / not placed and the
    reconciliation, for the session record and the result's header."""

    pipeline: Any  # backend.pipeline.Pipeline
    cameras: CameraSet
    initial_yaml: str | None
    config: EngineConfig
    taken: float
    hypotheses: int
    meta: dict[str, Any]
    index: dict[int, int] = field(repr=False)  # collector camera index -> pipeline camera index

    @staticmethod
    def build(job: BootstrapJob, result: BootstrapResult, cameras: CameraSet, config: EngineConfig,
              initial: bool, *, seed: int = 0, frames: Sequence[Frame] | None = None,
              reconciled: tuple[Any, str] | None = None) -> "Handover":
        """The pipeline from ``result`` (synchronous, seconds of numpy: run it in a thread).
        ``cameras``/``initial``: the session's camera set and whether its poses are an
        initial estimate (then reconciled with the bootstrap: frame and scale kept, as
        ``extrcal calibrate`` with ``bootstrap.with_initial``), else placeholders.
        ``frames``: what the pipeline takes (default the job's; live: everything collected
        until now, the attempt may have run for minutes). ``reconciled``: ``result``
        already reconciled with ``cameras`` (``reconcile_cameras``: the Reconciled or None,
        and its note), not done again."""
        from .pipeline import Pipeline
        from .reconcile import reconcile_cameras

        meta: dict[str, Any] = {"result": result.to_dict(),
                                "placed": [n for n, ok in zip(result.names, result.located) if ok],
                                "not_placed": [n for n, ok in zip(result.names, result.located) if not ok]}
        start = None
        initial_yaml = None
        if initial:
            if reconciled is None:
                rec, _, note = reconcile_cameras(result, cameras, config)
            else:
                rec, note = reconciled
            meta["reconciled"] = rec.to_dict() if rec is not None else None
            meta["note"] = note
            cams = cameras
            if rec is not None:
                config, cams, start = rec.applied(config, cameras)
            meta["frame"] = "the initial estimate's frame and scale"
            meta["not_placed"] = []  # they start from the initial estimate: calibrated all the same
        else:
            cams = camera_set(cameras.intrinsics, result)
            config = handover(config, result)
            initial_yaml = dump_extrinsics(dict(cams.extrinsics), comment=_header(result))
            meta["frame"] = result.frame
            meta["scale"] = result.scale.to_dict() if result.scale is not None else None
            meta["note"] = (f"the bootstrap placed {len(cams.names)}/{len(result.names)} cameras from "
                            f"{result.data_seconds:.0f} s of data")
        index = {job.names.index(n): k for k, n in enumerate(cams.names)}
        frames = job.frames if frames is None else frames
        if not initial and config.bootstrap.late and not result.located.all():
            # the cameras it did not place: archived beside the pipeline, resected when the session
            # stops (backend/late_join.py); the collector's framesets index all cameras, as it does
            from .late_join import JoiningPipeline

            p = JoiningPipeline(cams, config, intrinsics=cameras.intrinsics, names=job.names, seed=seed)
            p.take_late_frames(frames)
            meta["late"] = list(p.unplaced)
        else:  # an initial estimate's frame and scale are checked against the people's at the end
            p = Pipeline(cams, config, seed=seed, start=start, scale_heights=job.heights if initial else None)
        new = p.take_frames(remap(frames, index))
        taken = frames[-1][0] if frames else -math.inf
        return Handover(p, cams, initial_yaml, config, taken, new, meta, index)

    def catch_up(self, collector: "Collector | Any") -> int:
        """Feed the framesets the collector took while the handover was built, and take
        over its clock, counters and the point of time its sync has reached (so nothing
        is emitted twice); returns the new hypotheses. On the loop: cheap. ``collector``:
        a Collector, or the pipeline a live check of the initial estimate replaces (it
        has the same frames, clock, counters and sync)."""
        p = self.pipeline
        later = [f for f in collector.frames if f[0] > self.taken]
        new = p.take_frames(remap(later, self.index))
        late = getattr(p, "late_sync", None)
        if late is not None:  # a JoiningPipeline: its second front end goes on where the collector is
            p.take_late_frames(later)
            late.take_over(collector.sync)
        p.clock = collector.clock
        p.messages = collector.messages
        p.rejected = Counter(collector.rejected)
        p.last_seen = {n: s for n, s in collector.last_seen.items() if n in p.names or n in getattr(p, "unplaced", ())}
        p.sync.take_over(collector.sync)
        return new


def remap(frames: Sequence[Frame], index: dict[int, int]) -> list[Frame]:
    """Frames with their detections' camera indices mapped by ``index`` (collector →
    pipeline); views of cameras not in it dropped, frames left with < 2 views dropped."""
    if all(k == v for k, v in index.items()) and all(v[0].cam in index for _, views in frames for v in views if v):
        return list(frames)  # (a camera after the last one in ``index`` is not in it: no shortcut then)
    out = []
    for T, views in frames:
        vs = tuple(tuple(replace(d, cam=index[d.cam]) for d in v) for v in views if v and v[0].cam in index)
        if len(vs) >= 2:
            out.append((T, vs))
    return out


def compare(a: BootstrapResult, b: BootstrapResult) -> tuple[list[str], np.ndarray, np.ndarray] | None:
    """Two bootstrap results of the same cameras (each in its own floor frame and scale):
    ``b`` aligned onto ``a`` by a trimmed similarity of the centres they both placed
    (``geometry.trimmed_similarity``); per camera (names, translation (N,) m in a's units,
    rotation (N,) deg). None when fewer than 3 cameras are in both."""
    from .geometry import align_poses

    both = np.flatnonzero(a.located & b.located)
    if len(both) < 3 or a.names != b.names:
        return None
    al = align_poses(b.R[both], b.t[both], a.R[both], a.t[both])
    if al is None:
        return None
    return [a.names[c] for c in both], al.dt, al.dr


def _header(result: BootstrapResult) -> str:
    """What the result's header says of where its frame and scale come from."""
    lines = [f"no initial estimate: bootstrapped live from {result.data_seconds:.0f} s of data; {result.frame}"]
    if result.scale is not None:
        lines.append(f"metric scale from people: {result.scale.summary()}")
    else:
        lines.append("metric scale: the rough scale of the pairs' persons (no person measured well enough)")
    return "\n".join(lines)


class Collector:
    """The pipeline's stand-in while a session collects data for its bootstrap.

    It has what the service asks of a pipeline (push, advance, next_problem, clock_job,
    counters, state, snapshot, finish ...) and runs the pipeline's own front end: sync,
    preprocess, framesets with >= 2 views archived (``frames``, at most
    ``refine.archive_frames``). It has no poses, so no association and no cycles.
    """

    def __init__(self, cameras: CameraSet, config: EngineConfig, options: LiveOptions, *, initial: bool,
                 seed: int = 0):
        self.cameras = cameras
        self.cfg = config = config.for_images(cameras.sizes)
        self.options = options
        self.initial = initial  # the camera set's poses are an initial estimate (distrust_initial)
        self.seed = seed
        self.names = cameras.names
        C = len(self.names)
        self.focal = np.array([0.5 * (cameras.intrinsics[n].fx + cameras.intrinsics[n].fy) for n in self.names])
        self.sync = Synchronizer(config.sync, self.names)
        self.preprocess = Preprocessor(config.preprocess, self.names, cameras.intrinsics)
        self.stamps = StampWatch(config.clock.auto_lead)  # which sensors' stamps run apart (``bootstrap.stamps_apart``)
        self.frames: deque[Frame] = deque(maxlen=config.refine.archive_frames)
        self.clock: float | None = None
        self.messages = 0
        self.rejected: Counter = Counter()
        self.last_seen: dict[str, float] = {}
        self.cycle = 0
        self.last_report = None
        self.seen = np.zeros(C, dtype=np.int64)  # framesets with a detection, per camera
        self.pairs: Counter = Counter()  # (a, b) -> framesets in which each sees exactly one person
        self.first_time: float | None = None
        self.attempts: list[dict[str, Any]] = []
        self.running: BootstrapJob | None = None
        b = config.bootstrap
        self.deadline = b.max_seconds if b.max_seconds > 0 else b.live_first
        self.next_attempt = min(b.live_first, self.deadline)
        self.accepted: BootstrapResult | None = None
        self.previous: tuple[int, BootstrapResult] | None = None  # the last attempt with a result

    # ------------------------------------------------------------ the pipeline's front end

    def push(self, msg: KeypointMessage, arrival: float | None = None) -> str | None:
        """As ``Pipeline.push`` (live: ``arrival`` is the service clock)."""
        self.messages += 1
        reason = self.sync.push(msg, arrival)
        if reason is not None:
            self.rejected[reason] += 1
            return reason
        self.last_seen[msg.sensor] = msg.stamp
        self.stamps.observe(msg.sensor, msg.stamp)
        if arrival is None and (self.clock is None or msg.stamp > self.clock):
            self.clock = msg.stamp
        return None

    def advance(self, now: float | None, *, clock_offsets: bool = True) -> int:
        """Sync and preprocess up to ``now``; archives framesets; returns 0 (no hypotheses)."""
        if now is None:
            return 0
        if self.clock is None or now > self.clock:
            self.clock = now
        self.stamps.sample(now)
        for fs in self.sync.pop_ready(now):
            dets = self.preprocess(fs)
            if len(dets) < 2:
                continue
            views = tuple(tuple(v) for v in dets)
            self.frames.append((fs.time, views))
            if self.first_time is None:
                self.first_time = fs.time
            for v in views:
                self.seen[v[0].cam] += 1
            single = sorted(v[0].cam for v in views if len(v) == 1)
            for i in range(len(single)):
                for j in range(i + 1, len(single)):
                    self.pairs[(single[i], single[j])] += 1
        return 0

    def next_problem(self, now: float | None) -> None:
        return None  # no poses, no cycles

    def clock_job(self, now: float | None) -> None:
        return None  # the clock offsets need poses too

    def apply_clock(self, job: Any, result: Any) -> list[str]:
        return []

    def cancel_clock(self) -> None:
        pass

    def finish(self) -> CalibrationState:
        return self.state()

    def skeletons(self, n: int = 4) -> list:
        return []

    def std_note(self) -> str | None:
        return None  # no poses, no std

    def counters(self) -> Counters:
        return Counters(messages=self.messages, rejected=dict(self.rejected), framesets=self.sync.framesets,
                        framesets_rejected=dict(self.sync.framesets_rejected), views=self.preprocess.accepted,
                        views_rejected=dict(self.preprocess.rejected))

    def state(self) -> CalibrationState:
        """No camera has a pose yet: an empty estimate."""
        return CalibrationState(self.clock, 0, (), False, self.counters(), None)

    def snapshot(self) -> dict[str, Any]:
        """Nothing to resume from but the fact: a resumed session collects again."""
        return {"version": 2, "bootstrapping": True, "names": list(self.names), "clock": self.clock}

    # ------------------------------------------------------------ the bootstrap's phases

    @property
    def data_seconds(self) -> float:
        """s of data collected: the first to the newest archived frameset."""
        return self.frames[-1][0] - self.frames[0][0] if self.frames else 0.0

    def usable_pairs(self) -> int:
        """Camera pairs with ``min_pair_frames`` framesets in which each sees one person
        (the bootstrap's candidates; whether it is the same person it decides)."""
        m = self.cfg.bootstrap.min_pair_frames
        return sum(1 for n in self.pairs.values() if n >= m)

    def job(self) -> BootstrapJob | None:
        """The next attempt when it is due (and none is in flight), else None."""
        if self.running is not None or self.accepted is not None:
            return None
        secs = self.data_seconds
        if secs < self.next_attempt:
            return None
        job = BootstrapJob(len(self.attempts) + 1, tuple(self.frames), tuple(self.names), self.focal.copy(),
                           self.cfg, self.options.heights, self.seed, secs, self.seen.copy(),
                           final=secs >= self.deadline, mistimed=stamps_apart(self.stamps, self.cfg, len(self.names)))
        self.running = job
        return job

    def needed(self, job: BootstrapJob) -> int:
        """Cameras an attempt before the deadline must place: ``live_min_placed`` of those
        that saw people in ``min_pair_frames`` framesets (a camera that sees nobody must
        not hold the session back), at least 2."""
        b = self.cfg.bootstrap
        saw = int((job.seen >= b.min_pair_frames).sum())
        return max(2, math.ceil(b.live_min_placed * saw - 1e-9))

    def conclude(self, job: BootstrapJob, outcome: Outcome) -> BootstrapResult | None:
        """Judge an attempt: the result when accepted (the caller hands over), else None
        and the next attempt is scheduled ``live_interval`` s of data later (and at the
        deadline, if this one was before it)."""
        assert job is self.running, "conclude() of a job that is not in flight"
        self.running = None
        b = self.cfg.bootstrap
        att: dict[str, Any] = {"attempt": job.attempt, "data_seconds": round(job.data_seconds, 1),
                               "frames": len(job.frames), "seconds": round(outcome.seconds, 2)}
        res = outcome.result
        if res is None:
            att["accepted"] = False
            att["error"] = outcome.error or "no result"
        else:
            placed = int(res.located.sum())
            need = 2 if job.final else self.needed(job)
            att.update(placed=placed, needed=need, pairs=res.pairs, accepted=placed >= need)
            if not att["accepted"]:
                att["error"] = f"placed {placed} of {len(job.names)} cameras, {need} needed before " \
                               f"{self.deadline:g} s of data"
            elif not job.final and b.live_confirm:
                why = self._unconfirmed(res)
                if why:
                    att.update(accepted=False, error=why)
            self.previous = (job.attempt, res)
        self.attempts.append(att)
        if att["accepted"]:
            self.accepted = res
            return res
        nxt = job.data_seconds + b.live_interval
        if job.data_seconds < self.deadline:
            nxt = min(nxt, self.deadline)
        self.next_attempt = nxt
        return None

    def _unconfirmed(self, res: BootstrapResult) -> str | None:
        """Why an early result is not confirmed by the attempt before it (None: it is)."""
        b = self.cfg.bootstrap
        if self.previous is None:
            return f"placed {int(res.located.sum())} cameras; an early result is taken when the next attempt agrees"
        k, prev = self.previous
        cmp = compare(prev, res)
        if cmp is None:
            return f"fewer than 3 cameras in common with attempt {k}: to be confirmed by the next attempt"
        names, dt, dr = cmp
        bad = [(n, t, r) for n, t, r in zip(names, dt, dr) if t > b.live_confirm_translation or r > b.live_confirm_rotation]
        if bad:
            worst = ", ".join(f"{n} ({t:.2f} m / {r:.1f}°)" for n, t, r in sorted(bad, key=lambda x: -x[2])[:3])
            return f"disagrees with attempt {k} on {len(bad)} camera(s): {worst}"
        return None

    def reason(self) -> str:
        """The session's reason while it bootstraps, e.g. "bootstrapping: 45 s of 120 s
        collected, 12 pairs"."""
        secs = self.data_seconds
        head = (f"bootstrapping: {secs:.0f} s of {self.deadline:g} s collected, {self.usable_pairs()} pairs"
                if secs < self.deadline else
                f"bootstrapping: {secs:.0f} s collected ({self.deadline:g} s planned), {self.usable_pairs()} pairs")
        if self.running is not None:
            head += f"; bootstrap attempt {self.running.attempt} running on {self.running.data_seconds:.0f} s of data"
        elif self.accepted is not None:
            head += "; bootstrap done, handing over to the online pipeline"
        else:
            head += f"; next attempt at {self.next_attempt:.0f} s"
        if self.attempts and not self.attempts[-1]["accepted"]:
            head += f" (attempt {self.attempts[-1]['attempt']}: {self.attempts[-1]['error']})"
        if self.frames and not self.usable_pairs():
            head += "; no two cameras have seen one person together often enough yet"
        elif not self.frames:
            head = (f"bootstrapping: no frameset yet (needs {self.cfg.sync.min_views} sensors at one instant "
                    f"with a person)") + ("" if self.messages else "; no messages from the session's cameras yet")
        return head

    def progress(self) -> dict[str, Any]:
        """The phase with its figures, for the session record (``bootstrap``)."""
        phase = "bootstrapping" if self.running is not None else "collecting"
        return {"phase": phase, "data_seconds": round(self.data_seconds, 1), "target_seconds": self.deadline,
                "next_attempt": None if self.running is not None else self.next_attempt,
                "framesets": len(self.frames), "pairs": self.usable_pairs(),
                "cameras_seen": int((self.seen >= self.cfg.bootstrap.min_pair_frames).sum()),
                "attempts": list(self.attempts), "options": self.options.to_dict()}


def result_comment(bootstrap_record: dict[str, Any] | None) -> str:
    """Lines for a result's header from a session's ``bootstrap`` record: where the frame
    and the scale come from (as ``extrcal calibrate`` writes them), the cameras not placed."""
    b = bootstrap_record or {}
    if b.get("phase") != "done":
        return ""
    lines = []
    res = b.get("result") or {}
    if b.get("reconciled") is not None or b.get("frame") == "the initial estimate's frame and scale":
        lines.append(f"bootstrapped live (distrust_initial): {b.get('note', '')}")
    else:
        lines.append(f"no initial estimate: bootstrapped live from {res.get('data_seconds', 0):.0f} s of data; "
                     f"{b.get('frame', '')}")
        if res.get("mistimed"):
            lines.append(mistimed_summary(res["mistimed"]))
        sc = res.get("scale")
        if sc:
            lines.append(f"metric scale from people: scale {sc['factor']:.4f} ± {100 * sc['rel_std']:.1f} % from the "
                         f"{sc['method']} ({sc['persons']} persons: {', '.join(f'{h:.2f}' for h in sc['heights'])} m)")
    if b.get("placed_later"):
        from .late_join import later_summary

        lines += [later_summary(j) for j in b["placed_later"]]
    if b.get("not_placed"):
        lines.append(f"not placed by the bootstrap{' nor later' if b.get('placed_later') is not None else ''} "
                     f"(not calibrated): {', '.join(b['not_placed'])}")
    return "\n".join(lines)


def late_record(pipeline: Any, final: bool = True) -> dict[str, Any] | None:
    """After the final batch of a session whose bootstrap left cameras out (a
    ``JoiningPipeline``), or (``final`` False) when cameras joined it while it runs: what
    the session record's ``bootstrap`` says of them now (``placed_later``,
    ``late_resections``, the cameras still ``not_placed``, ``late_final``); None for
    another pipeline."""
    from .late_join import JoiningPipeline

    if not isinstance(pipeline, JoiningPipeline):
        return None
    return {"placed_later": [j.to_dict() for j in pipeline.late], "late_resections": list(pipeline.late_notes),
            "not_placed": pipeline.not_placed, "late_final": final}


def reason_suffix(bootstrap_record: dict[str, Any] | None) -> str:
    """What a calibrating session's reason adds: the cameras the bootstrap did not place."""
    b = bootstrap_record or {}
    if b.get("phase") == "done" and b.get("not_placed"):
        later = " (their data are kept: resected while it runs and when it stops)" if b.get("late") and \
            not b.get("late_final") else ""
        return f"; not placed by the bootstrap: {', '.join(b['not_placed'])}{later}"
    return ""
