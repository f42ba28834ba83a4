"""Cameras the bootstrap did not place join the calibration later (docs/bootstrap.md, session 6).

The bootstrap places a camera from its first ``bootstrap.max_seconds`` of data; a camera
that saw few people together with the placed cameras then (a corner people reach rarely
early on) is left out, and the online pipeline, which needs a pose for every camera it
associates, runs without it. Later data may place it: the same resection that placed
cameras no pair placed (``backend.resect``: RANSAC PnP of its detections against the
persons the placed cameras triangulate, with the same guards), now against the online
estimate over every frameset seen so far.

``JoiningPipeline`` is the online ``Pipeline`` of the placed cameras with a second front
end beside it: the same sync and preprocess over *all* cameras, which archives the
framesets in which a camera without a pose sees somebody (nothing else of the pipeline
sees them: association, cycles, clock offsets, monitor and scale run on the placed
cameras as before). When the run ends (``finish``: offline at the end of the recording,
live when the session stops) the unplaced cameras are resected against the final online
estimate; a camera that passes the guards joins a pipeline of the placed cameras and it
(``joined``: the placed cameras' state carried over, the new camera at its resected pose
with an honest, large std), and the final batch adjustment over all archived framesets
adjusts it with the others. Without a camera that passes, the final batch runs as in the
plain pipeline, on the same frames and seeds: the result does not change.

A camera without a pose has no clock offset estimated: the estimate needs its
associations. Its stamps are watched as the bootstrap watches them (``StampWatch``):
when they run apart from the others', it is resected both on its views as stamped and
on them its lead later (``retimed``), and joins timed as the one that agrees in more
framesets less those it disagrees in (docs/clock_offsets.md, Session 42); the pipeline
it joins applies that offset and estimates it from then on.

The numeric core: synchronous, no network.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from proto import KeypointMessage

from .bootstrap import Frame, retimed, stamps_apart, view_box
from .cameras import CameraSet, Extrinsics, Intrinsics, Pose
from .config import EngineConfig
from .geometry import R_to_quat
from .live_bootstrap import remap
from .pipeline import Pipeline
from .preprocess import Preprocessor
from .resect import SCALED_BY, Resection, resect_unplaced
from .stamp_watch import StampWatch
from .sync import Synchronizer

# The resection's own std (reprojections, one correlated block per detection) was 3-5x
# too small against the truth before the bundle adjustment (docs/bootstrap.md, Limits):
# the joined camera's prior in the final batch is this many times it, at least the
# hand-over's std of the placed cameras.
STD_FACTOR = 5.0
FLOOR_FRAMES = 400  # of the pipeline's framesets, evenly spread, for the network's floor in a late job


@dataclass(frozen=True)
class Joined:
    """A camera placed after the bootstrap: its name, the resection, the data seconds
    (first archived frameset to the last) it was resected on, and the prior std (m, deg)
    it entered the final batch with."""

    name: str
    resection: Resection
    data_seconds: float
    std_translation: float
    std_rotation: float
    adjusted: bool = False  # the final batch took it (else its resected pose is its result)
    live: bool = False  # it joined while the run went on (its cycles calibrated it), not when it ended
    paired_with: str = ""  # placed by its pair with this camera (``resect.place_by_pair``), not resected
    timed: float = 0.0  # s its views were taken later than stamped (its stamps' lead; 0: as stamped)

    def summary(self) -> str:
        return later_summary(self.to_dict())

    def to_dict(self) -> dict[str, Any]:
        r = self.resection
        return {"name": self.name, "data_seconds": round(self.data_seconds, 1), "frames": r.frames, "seen": r.seen,
                "spread": round(r.spread, 3) if np.isfinite(r.spread) else None, "residual_px": round(r.residual_px, 2),
                "std_translation": self.std_translation, "std_rotation": self.std_rotation, "paired_with": self.paired_with,
                "scaled_by": r.scaled_by,
                # the resected pose (translation, rotation quaternion x, y, z, w, as in the extrinsics YAML)
                "translation": r.t.tolist(), "rotation": R_to_quat(r.R).tolist(), "adjusted": self.adjusted,
                "live": self.live, "timed": self.timed}


class JoiningPipeline(Pipeline):
    """The online pipeline of the placed cameras (``cameras``), with the framesets of the
    cameras without a pose (the rest of ``intrinsics``) archived beside it, and their
    resection when it finishes (see the module doc). After ``finish``: ``joined`` is the
    pipeline that ran the final batch with the cameras placed late (None when none was),
    ``late`` their records, ``taken_back`` the ones left out of the result and
    ``late_notes`` one line per camera tried."""

    def __init__(self, cameras: CameraSet, config: EngineConfig | None = None, *,
                 intrinsics: Mapping[str, Intrinsics], names: Sequence[str], seed: int = 0,
                 start: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None):
        super().__init__(cameras, config, seed=seed, start=start)
        self.all_names = tuple(names)
        assert set(self.names) <= set(self.all_names), "the placed cameras must be among all cameras"
        self.all_intrinsics = {n: intrinsics[n] for n in self.all_names}
        self.unplaced = tuple(n for n in self.all_names if n not in self.names)
        self._unplaced_idx = frozenset(self.all_names.index(n) for n in self.unplaced)
        self.late_sync = Synchronizer(self.cfg.sync, self.all_names)
        self.late_preprocess = Preprocessor(self.cfg.preprocess, self.all_names, self.all_intrinsics,
                                            self.preprocess.confidence)
        # framesets (camera indices of all_names) in which an unplaced camera sees somebody
        self.late_frames: deque[Frame] = deque(maxlen=self.cfg.refine.archive_frames)
        self._late_pending: list[KeypointMessage] = []
        self._releasing = False
        self.joined: Pipeline | None = None
        self.late: list[Joined] = []
        self.taken_back: list[Joined] = []  # placed by a late pair that no cycle confirmed (``finish``)
        self.late_notes: list[str] = []
        self.late_archived = 0  # framesets ever archived in late_frames (a full deque stops growing)
        # every sensor's stamps as they arrive: the unplaced cameras' clocks are estimated by nobody
        self.late_stamps = StampWatch(self.cfg.clock.auto_lead)
        self._late_tried: float | None = None  # data time of the last resection while running
        self._late_seen = 0  # late_archived then

    @classmethod
    def resume(cls, cameras: CameraSet, config: EngineConfig, snapshot: dict, *, intrinsics: Mapping[str, Intrinsics],
               names: Sequence[str], seed: int = 0) -> "JoiningPipeline":
        """A session's pipeline after a restart (``Pipeline.restore``) that goes on archiving
        and resecting the cameras of ``names`` without a pose: the framesets archived before
        the restart are lost, new data may still place them."""
        p = cls(cameras, config, intrinsics=intrinsics, names=names, seed=seed)
        p._load(snapshot)
        return p

    # ------------------------------------------------------------ the second front end

    def push(self, msg: KeypointMessage, arrival: float | None = None) -> str | None:
        """As ``Pipeline.push``; a message of an unplaced camera goes to the second
        front end only (accepted: it is archived, not an unknown sensor)."""
        if msg.sensor in self.unplaced:
            self.messages += 1
            self.last_seen[msg.sensor] = msg.stamp
            reason = None
        else:
            reason = super().push(msg, arrival)
        if not self._releasing and self.unplaced:  # the held-back messages re-enter push: in _late_pending already
            self.late_stamps.observe(msg.sensor, msg.stamp)
            self._late_push(msg, arrival)
        return reason

    def _release_pending(self) -> str | None:
        self._releasing = True
        try:
            return super()._release_pending()
        finally:
            self._releasing = False

    def _late_push(self, msg: KeypointMessage, arrival: float | None) -> None:
        now = arrival if arrival is not None else self.clock
        if now is None:  # offline, before the clock is known (as the pipeline holds them back)
            self._late_pending.append(msg)
            return
        if self._late_pending:
            pending, self._late_pending = self._late_pending, []
            for m in sorted(pending, key=lambda m: m.stamp):
                self.late_sync.push(m, now)
        self.late_sync.push(msg, now)

    def advance(self, now: float | None, *, clock_offsets: bool = True) -> int:
        new = super().advance(now, clock_offsets=clock_offsets)
        if now is not None and self.unplaced:
            self._late_advance(now)
        return new

    def _late_advance(self, now: float) -> None:
        self.late_stamps.sample(now)
        if self._late_pending and self.clock is not None:
            pending, self._late_pending = self._late_pending, []
            for m in sorted(pending, key=lambda m: m.stamp):
                self.late_sync.push(m, self.clock)
        for fs in self.late_sync.pop_ready(now):
            # only framesets in which an unplaced camera sees somebody (the others are the pipeline's)
            if not any(v.sensor in self.unplaced and len(v.kp) for v in fs.views):
                continue
            dets = self.late_preprocess(fs)
            if len(dets) >= 2 and any(v[0].cam in self._unplaced_idx for v in dets):
                self.late_frames.append((fs.time, tuple(tuple(v) for v in dets)))
                self.late_archived += 1

    def take_late_frames(self, frames: Iterable[Frame]) -> int:
        """Framesets (camera indices of ``all_names``) from before this pipeline existed (the
        live bootstrap's collector): those with an unplaced camera's view are archived;
        returns how many."""
        n = 0
        for T, views in frames:
            if len(views) >= 2 and any(v and v[0].cam in self._unplaced_idx for v in views):
                self.late_frames.append((T, views))
                n += 1
        self.late_archived += n
        return n

    def _retime(self, sensors: list[str]) -> None:
        super()._retime(sensors)
        for name in sensors:  # the second front end times the placed cameras as the pipeline does
            self.late_sync.set_offset(name, float(self.sync.offset(name)))

    # ------------------------------------------------------------ the end of the run

    def finish(self):
        """As ``Pipeline.finish``; before the final batch the unplaced cameras are resected
        against the final online estimate, and those placed join it (``joined``)."""
        state = self._finish()
        final = self.joined if self.joined is not None else self
        self.late = [replace(x, adjusted=bool(final.refiner.cycles[final.names.index(x.name)] > 0))
                     if x.name in final.names else x for x in self.late]
        # A pair of cameras that each saw one person, two people, places a camera where it
        # looks at nobody the others see: no cycle takes it (too few views with them), and
        # its pose is the wrong pair's (a hall of 30, cam_22: 13.6 m / 70° off;
        # docs/bootstrap.md, Session 46). A right pair's camera sees the pair's person
        # with its partner again. Such a camera is left out, as one never placed.
        self.taken_back = unconfirmed(self.late)
        if self.taken_back:
            gone = {x.name for x in self.taken_back}
            self.late = [x for x in self.late if x.name not in gone]
            state = self.state()
        return state

    def _finish(self):
        cfg = self.cfg
        if not (cfg.refine.final_batch and self.unplaced):
            return super().finish()
        self.cfg = cfg.model_copy(update={"refine": cfg.refine.model_copy(update={"final_batch": False})})
        try:
            super().finish()  # both front ends flushed, the clock, the lost cameras: all but the batch
        finally:
            self.cfg = cfg
        if self.late_frames:
            self._join()
        if self.joined is not None:
            j = self.joined
            if j.frames:
                j.batch_adjust()
                j.check_halves_safely()
            self.final_batch_start, self.cycle, self.last_report = j.final_batch_start, j.cycle, j.last_report
            self.split_check, self.levelled, self.lenses = j.split_check, j.levelled, j.lenses
            return j.state()
        if self.frames:
            self.batch_adjust()
            self.check_halves_safely()
        return self.state()

    @property
    def not_placed(self) -> list[str]:
        """The unplaced cameras not placed late either, or taken back."""
        placed = {j.name for j in self.late}
        return [n for n in self.unplaced if n not in placed] + [x.name for x in self.taken_back]

    def state(self):
        """The joined pipeline's state once cameras joined at the end, else this one's (the
        cameras that joined while it ran among them); not the ones ``taken_back``."""
        state = self.joined.state() if self.joined is not None else super().state()
        gone = {x.name for x in self.taken_back}
        return replace(state, cameras=tuple(c for c in state.cameras if c.name not in gone)) if gone else state

    def snapshot(self) -> dict:
        return self.joined.snapshot() if self.joined is not None else super().snapshot()

    def far_from_start(self) -> list[tuple[str, float, float, float]]:
        return self.joined.far_from_start() if self.joined is not None else super().far_from_start()

    def _join(self) -> None:
        """Resect the unplaced cameras against the online estimate over the archived
        framesets; build ``joined`` when any passes the guards."""
        job = self._late_job()
        if self._accept(job, job.run()):
            self.joined = self._joined_pipeline()

    def _late_job(self) -> "LateJob":
        """The resection of the unplaced cameras against the current estimate, over the
        archived framesets in which they see somebody (a job for another process)."""
        names, C = self.all_names, len(self.all_names)
        idx = {n: k for k, n in enumerate(self.names)}
        rf = self.refiner
        R = np.repeat(np.eye(3)[None], C, axis=0)
        t = np.zeros((C, 3))
        located = np.zeros(C, dtype=bool)
        for c, n in enumerate(names):
            if n in idx:
                R[c], t[c], located[c] = rf.R[idx[n]], rf.t[idx[n]], True
        focal = np.array([0.5 * (self.all_intrinsics[n].fx + self.all_intrinsics[n].fy) for n in names])
        frames = tuple(self.late_frames)
        # the network's floor for a pair's baseline (``resect.place_by_pair``): where an
        # unplaced camera sees somebody the placed ones may see few people, so a spread of
        # the pipeline's own framesets too
        own = list(self.frames)[:: max(1, len(self.frames) // FLOOR_FRAMES)]
        floor_frames = tuple(remap(own, {c: names.index(n) for c, n in enumerate(self.names)}))
        leads = {names.index(n): v for n, v in stamps_apart(self.late_stamps, self.cfg, C).items() if n in self.unplaced}
        return LateJob(frames, R, t, located, focal, self.cfg.associate, self.cfg.bootstrap, self.cycle,
                       floor_frames, leads)

    def _accept(self, job: "LateJob", found: "LateResult", live: bool = False) -> list[Joined]:
        """The cameras a resection placed (``late``, ``late_notes``); returns the new ones."""
        names = self.all_names
        self.late_notes = [r.summary(names[r.cam], names) for r in found.resections]
        self.late_notes += [f"{names[c]}: {line}" for c, line in found.timing.items()]
        ok = [r for r in found.resections if r.accepted and found.located[r.cam] and names[r.cam] in self.unplaced]
        if not ok:
            return []
        frames = job.frames
        times = [f[0] for f in (frames[0], frames[-1], *(self.frames[k] for k in (0, -1) if self.frames))]
        seconds = max(times) - min(times)
        st0, sr0 = self.cfg.refine.initial_std_translation, self.cfg.refine.initial_std_rotation
        new = []
        for r in ok:
            cov = r.cov if r.cov is not None and np.all(np.isfinite(r.cov)) else None
            k = 1.0 if r.paired >= 0 else STD_FACTOR  # a pair's cov is stated, not a fit's (resect.place_by_pair)
            st = max(st0, k * float(np.sqrt(np.trace(cov[3:, 3:]) / 3))) if cov is not None else st0
            sr = max(sr0, k * float(np.degrees(np.sqrt(np.trace(cov[:3, :3]) / 3)))) if cov is not None else sr0
            new.append(Joined(names[r.cam], r, float(seconds), st, sr, live=live,
                              paired_with=names[r.paired] if r.paired >= 0 else "",
                              timed=float(found.timed.get(r.cam, 0.0))))
        for j in new:
            if j.timed:  # its archived views as the resection took them, its next ones timed so
                self.late_frames = deque(retimed(list(self.late_frames), names.index(j.name), j.timed),
                                         maxlen=self.late_frames.maxlen)
                self.late_sync.set_offset(j.name, j.timed)
        self.late += new
        return new

    # ------------------------------------------------------------ joining while the run goes on

    def late_join_due(self, now: float | None) -> bool:
        """A resection of the unplaced cameras is due while the run goes on: every
        ``bootstrap.late_join_interval`` s of data after the first adjustment, when they
        have new framesets, no cycle in flight."""
        iv = self.cfg.bootstrap.late_join_interval
        if iv <= 0 or now is None or not self.unplaced or self._inflight is not None or not self._calibrated():
            return False
        if self._late_tried is None:
            self._late_tried = now  # the first an interval after the first adjustment: the others settle
        return now - self._late_tried >= iv and self.late_archived > self._late_seen

    def late_job(self, now: float) -> "LateJob":
        """The job of a due resection (``LateJob.run`` in another process; its result to
        ``join_live``)."""
        self._late_tried, self._late_seen = now, self.late_archived
        return self._late_job()

    def join_live(self, job: "LateJob", found: "LateResult") -> "JoiningPipeline | None":
        """The cameras the job placed join: returns the pipeline to go on with (this one's
        estimate, archive, clock and counters, the new cameras at their resected pose with
        the prior std ``Joined`` says, the front end taken over), or None when none was
        placed. The caller swaps it in for this one; nothing may be in flight. What it
        starts afresh: the hypothesis queue (the archive has their data), the clock
        offsets' samples (the offsets applied are kept) and the monitor's watch."""
        assert self._inflight is None, "a camera joins between cycles"
        new = self._accept(job, found, live=True)
        if not new:
            return None
        cams, snap = self._grown()
        names = cams.names
        q = JoiningPipeline(cams, self.cfg, intrinsics=self.all_intrinsics, names=self.all_names)
        q._load(snap)
        self._carry_over(q)
        q.last_cycle_time, q.first_gated, q.cycle_gated = self.last_cycle_time, self.first_gated, self.cycle_gated
        q.cycles_rejected, q.last_report = self.cycles_rejected, self.last_report
        old = {n: k for k, n in enumerate(self.names)}
        q.sync.take_over(self.sync)
        q.sync.take_buffers(self.late_sync, [j.name for j in new])
        q.preprocess.take_counts(self.preprocess)  # the session's counts go on
        q.associate = self.associate
        q._recalibrate_due = [(due, names.index(self.names[c]), since) for due, c, since in self._recalibrate_due]
        for k in ("detected", "associated", "detected_total", "associated_total", "associated_multi"):
            arr = getattr(self, k)  # what the lost-camera and pairwise-only checks count on
            setattr(q, k, np.array([arr[old[n]] if n in old else 0 for n in names], dtype=np.int64))
        q.last_lost_check = self.last_lost_check
        # the monitor starts afresh: its watch too (the converged are watched again after a cycle)
        q.watched[:] = False
        q.refiner.held[:] = False
        q.late_sync.take_over(self.late_sync)
        q.late_preprocess, q.late_frames, q._late_pending = self.late_preprocess, self.late_frames, self._late_pending
        q.late, q.late_notes = list(self.late), list(self.late_notes)
        q.late_archived, q._late_tried, q._late_seen = self.late_archived, self._late_tried, self._late_seen
        return q

    def _grown(self) -> tuple[CameraSet, dict]:
        """The camera set and snapshot of this pipeline's cameras and those placed late
        that it does not have: its cameras' state carried over, the new ones at their
        resected pose with their prior std (``Joined``)."""
        late = {j.name: j for j in self.late if j.name not in self.names}
        names = tuple(n for n in self.all_names if n in self.names or n in late)
        old = {n: k for k, n in enumerate(self.names)}
        ext = dict(self.cameras.extrinsics)
        for n, j in late.items():
            res = self.all_intrinsics[n].resolution
            ext[n] = Extrinsics(Pose(j.resection.R.copy(), j.resection.t.copy()), res, j.std_translation,
                                j.std_rotation)
        cams = CameraSet.combine({n: self.all_intrinsics[n] for n in names}, {n: ext[n] for n in names})
        assert cams.names == names
        snap = Pipeline.snapshot(self)  # this pipeline's own, not a joined one's
        rf = self.refiner

        def grow(arr: np.ndarray, new) -> list:
            return [arr[old[n]].tolist() if n in old else new(n) for n in names]

        def cov(n: str) -> list:
            j = late[n]
            r = np.radians(j.std_rotation)
            return np.diag([r * r] * 3 + [j.std_translation ** 2] * 3).tolist()

        pose_R = lambda n: late[n].resection.R.tolist()  # noqa: E731
        pose_t = lambda n: late[n].resection.t.tolist()  # noqa: E731
        snap.update({
            "names": list(names),
            "R": grow(rf.R, pose_R), "t": grow(rf.t, pose_t), "P": grow(rf.P, cov), "S": grow(rf.S, cov),
            "R0": grow(rf.R0, pose_R), "t0": grow(rf.t0, pose_t),
            "prior_R": grow(rf.prior_R, pose_R), "prior_t": grow(rf.prior_t, pose_t), "P0": grow(rf.P0, cov),
            "cycles": [int(rf.cycles[old[n]]) if n in old else 0 for n in names],
            "history": [snap["history"][old[n]] if n in old else [] for n in names],
            "moved": [[a[0], names.index(self.names[int(a[1])]), *a[2:]] for a in snap["moved"]],
            "watched": [bool(self.watched[old[n]]) if n in old else False for n in names],
            "batched": [bool(rf.batched[old[n]]) if n in old else False for n in names],
            "observations": [int(self.observations[old[n]]) if n in old else 0 for n in names],
            "observations_batch": [int(self.observations_batch[old[n]]) if n in old else 0 for n in names],
            "lens_cov": None if snap.get("lens_cov") is None else
            [snap["lens_cov"][old[n]] if n in old else None for n in names],
        })
        timed = {n: j.timed for n, j in late.items() if j.timed}
        if timed:  # applied and estimated on from there (``Pipeline.restore``)
            snap["clock_offsets"] = {**snap["clock_offsets"], **timed}
            snap["clock_estimating"] = True
        return cams, snap

    def _merged_frames(self, names: tuple[str, ...]) -> deque:
        """The archived framesets of both front ends, re-indexed to ``names``."""
        new = {n: k for k, n in enumerate(names)}
        from_all = {c: new[n] for c, n in enumerate(self.all_names) if n in new}
        from_placed = {c: new[n] for c, n in enumerate(self.names)}
        rate = self.cfg.sync.rate
        merged: dict[int, Frame] = {}
        for T, views in remap(list(self.frames), from_placed):
            merged[round(T * rate)] = (T, views)
        for T, views in remap(list(self.late_frames), from_all):
            k = round(T * rate)
            if k in merged:  # the same instant: the pipeline's views (timed as it timed them) and the late cameras'
                have = {v[0].cam for v in merged[k][1]}
                views = tuple(sorted(merged[k][1] + tuple(v for v in views if v[0].cam not in have),
                                     key=lambda v: v[0].cam))
            merged[k] = (T, views)
        return deque((merged[k] for k in sorted(merged)), maxlen=max(self.cfg.refine.archive_frames, len(merged)))

    def _joined_pipeline(self) -> Pipeline:
        """A pipeline of this one's cameras and those placed late (``_grown``), with the
        archived framesets of both front ends merged: the final batch's."""
        cams, snap = self._grown()
        p = Pipeline.restore(cams, self.cfg, snap)
        self._carry_over(p)
        # the front end's counters are this pipeline's (nothing is pushed to the joined one)
        p.sync, p.preprocess, p.associate, p.queue = self.sync, self.preprocess, self.associate, self.queue
        return p

    def _carry_over(self, p: Pipeline) -> None:
        """What a pipeline grown by cameras placed late (``_grown``, restored) takes from
        this one besides the estimate: the seed's generator (its batches draw as this
        one's would), clock and message counts, the offsets' history and raw messages
        (the late cameras' start empty: no offset of theirs was applied), and the
        archived framesets of both front ends merged."""
        old = {n: k for k, n in enumerate(self.names)}
        p.rng, p.clock = self.rng, self.clock
        p.messages, p.rejected, p.last_seen = self.messages, self.rejected, dict(self.last_seen)
        p.relocalized = list(self.relocalized)
        timed = {j.name: j.timed for j in self.late}
        # a late camera's archived views: timed by its lead from the first (``_accept``), or as stamped
        p._offset_history = [list(self._offset_history[old[n]]) if n in old else
                             [(-np.inf, timed[n])] if timed.get(n) else [] for n in p.names]
        if self.raw is not None and p.raw is not None:
            p.raw = self.raw.keep(p.names)
        p.frames = self._merged_frames(p.names)


@dataclass(frozen=True)
class LateResult:
    """What a ``LateJob`` found: per camera tried its resection; (C,) bool the cameras of
    ``all_names`` located after it."""

    resections: tuple[Resection, ...]
    located: np.ndarray
    timed: Mapping[int, float] = field(default_factory=dict)  # camera -> s its views were taken later
    timing: Mapping[int, str] = field(default_factory=dict)  # camera whose stamps ran apart -> how each
    # timing agreed and which was taken


@dataclass(frozen=True, eq=False)
class LateJob:
    """A resection of the unplaced cameras (``resect_unplaced``) with what it reads: the
    late framesets (camera indices of all cameras), every camera's pose (C, 3, 3), (C, 3)
    where ``located`` (C,) bool, focal lengths (C,) px, the configs, a seed, some of
    the pipeline's own framesets for the placed cameras' floor, and the leads (s) of the
    unplaced cameras whose stamps run apart from the others' (``bootstrap.stamps_apart``):
    each is resected as stamped and timed by its lead, and keeps the better
    (``LateResult.timed``)."""

    frames: tuple[Frame, ...]
    R: np.ndarray
    t: np.ndarray
    located: np.ndarray
    focal: np.ndarray
    associate: Any
    bootstrap: Any
    seed: int
    floor_frames: tuple[Frame, ...] = ()  # the placed cameras' framesets (all cameras' indices) for their floor
    leads: Mapping[int, float] = field(default_factory=dict)  # unplaced cameras whose stamps run apart: s

    def run(self) -> LateResult:
        located, found = self._resect(list(self.frames))
        if not self.leads:
            return LateResult(tuple(found), located)
        # A lead is a clock's offset or a longer delay (backend/stamp_watch.py): the
        # resections on the views as stamped and on them that much later tell which, by
        # the framesets each agrees in less those it disagrees in. Agreeing framesets alone
        # favour the stamps: the views taken later are interpolated, so fewer (measured:
        # +200 ms clock, 34 of 49 as stamped, 27 of 28 timed; a 200 ms delay, 61 of 61 as
        # stamped, 28 of 31 timed; docs/clock_offsets.md, Session 42). A tie: as stamped.
        frames = list(self.frames)
        for c, lead in self.leads.items():
            frames = retimed(frames, c, lead)
        alt_located, alt = self._resect(frames)
        by_cam = {r.cam: r for r in alt}
        out, timed, timing = [], {}, {}
        for r in found:
            a = by_cam.get(r.cam)
            taken = (r.cam in self.leads and a is not None and a.accepted and (not r.accepted or _net(a) > _net(r)))
            out.append(a if taken else r)
            if taken:
                located[r.cam], timed[r.cam] = alt_located[r.cam], self.leads[r.cam]
            if r.cam in self.leads:
                timing[r.cam] = _timing_note(r, a, self.leads[r.cam], taken)
        return LateResult(tuple(out), located, timed, timing)

    def _resect(self, frames: list[Frame]) -> tuple[np.ndarray, list[Resection]]:
        C = len(self.located)
        _, _, located, found = resect_unplaced(frames, self.R, self.t, self.located, self.focal, view_box(frames, C),
                                               self.associate, self.bootstrap, seed=self.seed,
                                               pairs=self.bootstrap.late_pairs, floor_frames=self.floor_frames)
        return located, found


def _net(r: Resection) -> int:
    """A resection's framesets that agree with its pose less those that do not."""
    return 2 * r.frames - r.seen


def _timing_note(stamped: Resection, timed: Resection | None, lead: float, taken: bool) -> str:
    """How a camera whose stamps ran apart agreed each way (``LateResult.timing``)."""
    def agreed(r: Resection | None) -> str:
        return "no pose" if r is None or r.R is None else f"{r.frames}/{r.seen}" + ("" if r.accepted else " (refused)")

    return (f"its stamps ran {1000 * lead:+.0f} ms from the others': as stamped it agrees in "
            f"{agreed(stamped)}, timed by that lead in {agreed(timed)}: "
            + ("timed by it (its clock's offset)" if taken else "as stamped"))


def run_late_job(job: LateJob) -> LateResult:
    """``job.run()``, for a worker process."""
    return job.run()


def unconfirmed(late: Sequence[Joined]) -> list[Joined]:
    """The cameras a late pair placed while the run went on (``Joined.live``) that no
    cycle and not the final batch took (``Joined.adjusted``): where the pair put them
    they see nobody the others see (``JoiningPipeline.finish`` takes them back)."""
    return [x for x in late if x.paired_with and x.live and not x.adjusted]


def later_summary(j: Mapping[str, Any]) -> str:
    """One line for a camera placed after the bootstrap, from ``Joined.to_dict`` (the
    result's header, offline and live)."""
    how = (f" by its pair with {j['paired_with']} over {j['data_seconds']:.0f} s of data (agrees in "
           f"{j['frames']}/{j['seen']} frames in which each sees one person, {j['residual_px']:.1f} px; "
           f"{SCALED_BY.get(j.get('scaled_by', ''), 'its baseline scaled by the people')}), " if j.get("paired_with") else
           f": resected against the online estimate over {j['data_seconds']:.0f} s of data (agrees in "
           f"{j['frames']}/{j['seen']} framesets, spread {j['spread']:.2f} m, {j['residual_px']:.1f} px), ")
    if j.get("timed"):
        how += f"timed by its stamps' lead ({1000 * j['timed']:+.0f} ms: its clock's offset, not a delay), "
    prior = f"from a prior std of {j['std_translation']:.3f} m / {j['std_rotation']:.2f}°"
    if j.get("live") and j.get("adjusted"):
        then = f"joined the running calibration (its cycles and the final batch adjusted it) {prior}"
    elif j.get("live"):  # too few views with the others for a cycle: a wrong pair's camera looks where they see nobody
        then = ("joined the running calibration, but no cycle and not the final batch adjusted it (too few views "
                f"with the others): its {'pair' if j.get('paired_with') else 'resection'}'s pose is its result, "
                "unconfirmed")
    elif j.get("adjusted"):
        then = f"then adjusted by the final batch adjustment with the others {prior}"
    else:
        then = "not adjusted (the final batch adjustment was not taken: its resected pose is its result)"
    return f"{j['name']} placed after the bootstrap" + how + then


def late_comment(p: Pipeline) -> list[str]:
    """Lines for a result's header: the cameras placed after the bootstrap, how; those
    tried and not placed."""
    if not isinstance(p, JoiningPipeline):
        return []
    lines = [j.summary() for j in p.late]
    lines += [f"{j.name} placed by its pair with {j.paired_with} after the bootstrap, then taken back: no cycle took "
              "it (too few views with the others, as where a pair of two people put a camera)" for j in p.taken_back]
    if p.not_placed:
        lines.append(f"not placed by the bootstrap nor later (not calibrated): {', '.join(p.not_placed)}")
    return lines
