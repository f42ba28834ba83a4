"""The simulator: walkers in a scene seen by free-running, imperfect sensors.

The run advances in chunks of two seconds of true time: the world computes its ticks,
each sensor captures its frames and detects, and messages leave in arrival order
through a small heap (only messages that may still be overtaken wait). Memory stays
bounded however long the run; ``duration`` may be ``math.inf``.
"""

from __future__ import annotations

import heapq
import math
import os
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from proto import KeypointMessage, RecordingWriter

from .area import Area, build_area, wall_map
from .config import SimConfig
from .scene import Scene
from .sensors import FLAG_DUPLICATE, FLAG_SNAP, FLAG_SWAP, Detection, SensorSim, to_message
from .stats import SimStats, StatsCollector
from .truth import STATE_NAMES, Truth, interpolate
from .world import World

CHUNK = 2.0  # s of true time per step of the run


@dataclass
class _Record:
    """Truth and statistics gathered along a run."""

    names: tuple[str, ...]
    ticks_J: list = field(default_factory=list)
    ticks_S: list = field(default_factory=list)
    msg: list = field(default_factory=list)  # (sensor idx, seq, capture, stamp, arrival)
    det: list = field(default_factory=list)  # (msg idx, index, person, flags)
    sensors: list = field(default_factory=list)  # the run's SensorSim objects (their counters)
    heights: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        self.stats = StatsCollector(self.names)


class Simulator:
    """People walking through ``scene``, seen by its cameras as edge sensors would report.

    sim = Simulator(scene, SimConfig(persons=2, duration=180.0, seed=0))
    for arrival, msg in sim.messages(): ...      # all sensors, arrival order
    for arrival, msg in sim.messages(["cam_3"]): ...  # one sensor: the same messages
    stats = sim.write("rec.jsonl.gz")            # recording + rec.jsonl.gz.truth.npz
    sim.truth                                    # Truth of the full run (finite runs)
    """

    def __init__(self, scene: Scene, config: SimConfig | None = None):
        self.scene = scene
        self.config = config if config is not None else SimConfig()
        named = {"clock_offsets": [k for k, _ in self.config.clock_offsets],
                 "clock_drifts": [k for k, _ in self.config.clock_drifts],
                 "bumps": [b[1] for b in self.config.bumps]}
        for what, names in named.items():
            unknown = sorted(set(names) - set(scene.names))
            if unknown:
                raise ValueError(f"SimConfig.{what}: unknown sensors {', '.join(unknown)} "
                                 f"(scene has {', '.join(scene.names)})")
        self.area: Area | None = build_area(scene, self.config.coverage_range) if self.config.persons else None
        self._truth: Truth | None = None
        self._stats: SimStats | None = None

    # ------------------------------------------------------------------ public

    def messages(self, sensors: Iterable[str] | None = None) -> Iterator[tuple[float, KeypointMessage]]:
        """(arrival epoch s, message) in arrival order, computed as they are needed.

        sensors: restrict to these sensor ids (each sensor's messages are identical to
        those of the all-sensor run). Unknown ids raise ValueError.
        """
        for arrival, msg, _ in self._run(self._select(sensors), None):
            yield arrival, msg

    @property
    def truth(self) -> Truth:
        """Ground truth of the whole (finite) run; computed by a run of its own unless
        ``write`` has already produced it."""
        if self._truth is None:
            rec = self._record_run(None)
            self._truth, self._stats = self._finish(rec)
        return self._truth

    @property
    def stats(self) -> SimStats:
        if self._stats is None:
            _ = self.truth
        assert self._stats is not None
        return self._stats

    def write(self, out_path: str | os.PathLike) -> SimStats:
        """Write the recording (.jsonl, .jsonl.gz, .msgpack by the name) and its truth
        sidecar ``<out_path>.truth.npz``; return the run's figures."""
        out = Path(out_path)
        out.parent.mkdir(parents=True, exist_ok=True)
        with RecordingWriter(out) as w:
            rec = self._record_run(w.write)
        self._truth, self._stats = self._finish(rec)
        self._truth.save(Truth.sidecar_path(out))
        return self._stats

    # ------------------------------------------------------------------ internals

    def _select(self, sensors: Iterable[str] | None) -> list[str]:
        if sensors is None:
            return list(self.scene.names)
        if isinstance(sensors, str):
            sensors = [sensors]
        want = list(dict.fromkeys(sensors))
        unknown = [s for s in want if s not in self.scene.intrinsics]
        if unknown:
            raise ValueError(f"unknown sensors {', '.join(unknown)} (scene has {', '.join(self.scene.names)})")
        return [n for n in self.scene.names if n in want]

    def _make_sensors(self, names: list[str]) -> list[SensorSim]:
        walls = wall_map(self.scene)
        floor = self.scene.floor
        return [SensorSim(n, self.scene.names.index(n), self.scene.intrinsics[n], self.scene.poses[n],
                          self.config, walls, floor.R, floor.origin) for n in names]

    def _record_run(self, sink) -> _Record:
        if math.isinf(self.config.duration):
            raise ValueError("an endless run (duration = inf) has no complete truth; use messages()")
        rec = _Record(self.scene.names)
        for _, msg, dets in self._run(list(self.scene.names), rec):
            if sink is not None:
                sink(msg)
            rec.stats.add(msg.sensor, dets)
        return rec

    def _run(self, names: list[str], rec: _Record | None) -> Iterator[tuple[float, KeypointMessage, list[Detection]]]:
        cfg = self.config
        sensors = self._make_sensors(names)
        world = World(self.scene, cfg, self.area) if cfg.persons else None
        if rec is not None:
            rec.sensors = sensors
            rec.heights = world.heights if world is not None else np.zeros(0)
        rate = cfg.world_rate
        # Capture jitter moves a frame at most 0.3 periods; the margin depends on the
        # configuration only, so that any subset of sensors sees the same world chunks.
        slowest = min([cfg.rates[0]] + [r for _, r in cfg.sensor_rates])
        margin = 0.3 / slowest + 0.05
        heap: list = []
        c = 0
        while True:
            t0, t1 = c * CHUNK, (c + 1) * CHUNK
            if t0 >= cfg.duration:
                break
            frames = [s.frames_until(t1) for s in sensors]
            if world is not None:
                J, S = world.advance(int(math.ceil((t1 + margin) * rate)) + 1)
                if rec is not None:
                    rec.ticks_J.append(J)
                    rec.ticks_S.append(S)
                wt, wJ = world.window_times(), world.J
            for s, frs in zip(sensors, frames):
                if not frs:
                    continue
                caps = np.array([f.capture for f in frs])
                if world is not None:
                    Jc = interpolate(wt, wJ, caps)
                else:
                    Jc = np.zeros((len(frs), 0, 17, 3))
                for fr, dets in zip(frs, s.detect(frs, Jc)):
                    msg = to_message(s.name, fr, s.size, dets)
                    heapq.heappush(heap, (fr.arrival, s.index, fr.seq, msg, dets, fr))
            if world is not None:
                world.drop_before(int(math.floor((t1 - margin) * rate)) - 1)
            # Every later frame is captured after t1 - margin and arrives after that.
            safe = cfg.start_time + t1 - margin
            while heap and heap[0][0] <= safe:
                yield self._emit(heapq.heappop(heap), rec)
            c += 1
        while heap:
            yield self._emit(heapq.heappop(heap), rec)

    @staticmethod
    def _emit(item, rec: _Record | None):
        arrival, idx, seq, msg, dets, fr = item
        if rec is not None:
            m = len(rec.msg)
            rec.msg.append((idx, seq, fr.capture, fr.stamp, arrival))
            for i, d in enumerate(dets):
                rec.det.append((m, i, d.person, d.flags))
        return arrival, msg, dets

    def _finish(self, rec: _Record) -> tuple[Truth, SimStats]:
        cfg, scene = self.config, self.scene
        P = cfg.persons
        if rec.ticks_J:
            J = np.concatenate(rec.ticks_J, axis=1)
            S = np.concatenate(rec.ticks_S, axis=1)
        else:
            J, S = np.zeros((P, 0, 17, 3)), np.zeros((P, 0, len(STATE_NAMES)))
        T = J.shape[1]
        if P == 0:
            T = int(math.ceil(cfg.duration * cfg.world_rate)) + 2
            J, S = np.zeros((0, T, 17, 3)), np.zeros((0, T, len(STATE_NAMES)))
        times = cfg.start_time + np.arange(T, dtype=np.float64) * (1.0 / cfg.world_rate)
        det = np.array(rec.det, dtype=np.int64).reshape(-1, 4)
        msg_sensor = np.array([m[0] for m in rec.msg], dtype=np.int32)
        msg_seq = np.array([m[1] for m in rec.msg], dtype=np.int64)
        msg_capture = np.array([m[2] for m in rec.msg], dtype=np.float64)
        det_msg = det[:, 0]
        sensors = rec.sensors
        truth = Truth(
            sensors=tuple(scene.names),
            start_time=float(cfg.start_time),
            seed=int(cfg.seed),
            config=cfg.to_dict(),
            times=times,
            joints=J,
            heights=np.asarray(rec.heights, float),
            states=S,
            msg_sensor=msg_sensor,
            msg_seq=msg_seq,
            msg_capture=msg_capture,
            msg_stamp=np.array([m[3] for m in rec.msg], dtype=np.float64),
            msg_arrival=np.array([m[4] for m in rec.msg], dtype=np.float64),
            det_msg=det_msg,
            det_sensor=msg_sensor[det_msg],
            det_seq=msg_seq[det_msg],
            det_index=det[:, 1].astype(np.int32),
            det_person=det[:, 2].astype(np.int32),
            det_capture=msg_capture[det_msg],
            det_flags=det[:, 3].astype(np.uint8),
            clock_offset=np.array([s.offset for s in sensors]),
            clock_drift=np.array([s.drift for s in sensors]),
            capture_rate=np.array([s.rate for s in sensors]),
            delay_base=np.array([s.delay_base for s in sensors]),
            lens_fx=np.array([s.intr.fx for s in sensors]),
            lens_fy=np.array([s.intr.fy for s in sensors]),
            lens_cx=np.array([s.intr.cx for s in sensors]),
            lens_cy=np.array([s.intr.cy for s in sensors]),
            floor_origin=scene.floor.origin.copy(),
            floor_e1=scene.floor.e1.copy(),
            floor_e2=scene.floor.e2.copy(),
            floor_up=scene.floor.up.copy(),
            **_bump_truth(sensors, cfg.start_time),
        )
        return truth, self._make_stats(truth, rec)

    def _make_stats(self, truth: Truth, rec: _Record) -> SimStats:
        from .sensors import GROUP_NAMES

        cfg = self.config
        st = rec.stats
        names = self.scene.names
        S = len(names)
        # cameras detecting each person per 0.2 s bin of true time
        nb = max(1, int(math.ceil(cfg.duration / 0.2)))
        hist = np.zeros(S + 1)
        real = truth.det_person >= 0
        for p in range(truth.persons):
            sel = real & (truth.det_person == p)
            b = np.clip(((truth.det_capture[sel] - cfg.start_time) / 0.2).astype(np.int64), 0, nb - 1)
            pairs = np.unique(b * S + truth.det_sensor[sel])
            counts = np.bincount(pairs // S, minlength=nb)
            hist += np.bincount(counts, minlength=S + 1)[: S + 1]
        share = hist / hist.sum() if hist.sum() else hist
        flags = truth.det_flags
        original = (flags & FLAG_DUPLICATE) == 0  # a duplicate's flags are its original's
        tot = sum((s.counters for s in rec.sensors), Counter())
        rms = {g: float(np.sqrt(tot[f"sq{i}"] / tot[f"n{i}"])) if tot[f"n{i}"] else float("nan")
               for i, g in enumerate(GROUP_NAMES)}
        det = max(tot["detections"], 1)
        return SimStats(
            duration=float(cfg.duration),
            persons=truth.persons,
            heights=tuple(float(h) for h in truth.heights),
            messages=dict(st.messages),
            with_person={n: st.with_person[n] / st.messages[n] if st.messages[n] else 0.0 for n in names},
            rates={s.name: s.rate for s in rec.sensors},
            detections=int(tot["detections"]),
            false_detections=st.false,
            missed=int(tot["missed"]),
            swaps=int(np.sum(((flags & FLAG_SWAP) > 0) & original)),
            snaps=int(np.sum(((flags & FLAG_SNAP) > 0) & original)),
            guessed_joints=int(tot["guessed"]),
            visible_joints=tot["joints"] / det,
            confident_joints=tot["confident"] / det,
            cameras_seeing={k: float(share[k]) for k in range(S + 1)},
            noise_rms=rms,
            clock_offset_ms={s.name: 1000 * s.offset for s in rec.sensors},
            delay_ms={s.name: 1000 * s.delay_base for s in rec.sensors},
            duplicates=int(tot["duplicates"]),
        )


def _bump_truth(sensors: list[SensorSim], start_time: float) -> dict[str, np.ndarray]:
    """The Truth's bump_* arrays, in time order."""
    rows = sorted(((tb, s.index, disp, rot, pose) for s in sensors for tb, disp, rot, pose in s.bumps),
                  key=lambda r: (r[0], r[1]))
    return {
        "bump_sensor": np.array([r[1] for r in rows], dtype=np.int32),
        "bump_time": np.array([start_time + r[0] for r in rows], dtype=np.float64),
        "bump_translation": np.array([r[2] for r in rows], dtype=np.float64).reshape(-1, 3),
        "bump_rotation": np.array([r[3] for r in rows], dtype=np.float64).reshape(-1, 3),
        "bump_R": np.array([r[4].R for r in rows], dtype=np.float64).reshape(-1, 3, 3),
        "bump_t": np.array([r[4].t for r in rows], dtype=np.float64).reshape(-1, 3),
    }
