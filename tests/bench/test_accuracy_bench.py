"""bench/accuracy.py's ``--oracle``: the engine's associations kept to the true persons."""

from __future__ import annotations

import importlib.util
import sys
from collections import Counter
from pathlib import Path

import numpy as np

from backend.associate import Associator
from backend.bootstrap import collect_frames
from backend.config import EngineConfig
from edge_clients.sim import SimConfig, Simulator, Truth
from edge_clients.sim.scenes import tworooms
from proto import read_recording

REPO = Path(__file__).resolve().parents[2]


def _bench():
    spec = importlib.util.spec_from_file_location("accuracy_bench", REPO / "bench" / "accuracy.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["accuracy_bench"] = mod  # its dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def test_the_oracle_keeps_each_hypothesis_to_one_true_person_and_lets_go(tmp_path):
    """Four walkers in the two rooms, 20 s, at the true poses: the plain association
    mixes persons (two walkers each seen by one camera, their rays crossing near the
    wall); with the oracle open no hypothesis does, and every view it kept is a real
    person's. Closed, the association is the plain one again."""
    bench = _bench()
    scene = tworooms()
    sim = Simulator(scene, SimConfig(persons=4, duration=20.0, seed=0))
    rec = tmp_path / "rec.jsonl.gz"
    sim.write(rec)
    truth = Truth.load(Truth.sidecar_path(rec))
    names = list(scene.names)
    cfg = EngineConfig().for_images(i.resolution for i in scene.intrinsics.values())
    frames = collect_frames(tuple(names), scene.intrinsics, cfg, read_recording(rec))
    R = np.array([scene.poses[n].R for n in names])
    t = np.array([scene.poses[n].t for n in names])
    person = bench.true_persons(truth, names)

    def persons_of(hyps_dets):
        return [{person.get((d.cam, d.seq, d.index), -1) for d in dets} for dets in hyps_dets]

    def associate() -> list[list]:
        got, plain = [], Associator._hypothesis

        def record(self, time_, dets, *args, **kwargs):  # the views a hypothesis was made of
            h = plain(self, time_, dets, *args, **kwargs)
            if h is not None:
                got.append([d for d in dets if d.cam in set(h.cams.tolist())])
            return h

        Associator._hypothesis = record
        try:
            for time_, views in frames:
                Associator(cfg.associate)(time_, views, R, t)
        finally:
            Associator._hypothesis = plain
        return got

    plain = associate()
    assert sum(len(p) > 1 or -1 in p for p in persons_of(plain)) > 0  # the case the oracle is for
    with bench.true_association(truth, names) as seen:
        told = associate()
    assert told and all(len(p) == 1 and -1 not in p for p in persons_of(told))
    assert 0 < seen["dropped"] < seen["views"]
    assert Counter(len(p) for p in persons_of(associate())) == Counter(len(p) for p in persons_of(plain))
