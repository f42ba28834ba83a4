"""kill -9 of a real `extrcal serve` at random moments, with simulated sensors feeding a
session through Zenoh: after every kill each session file parses (atomic writes; only
the last history line may be torn), and the restarted daemon resumes the session from
the snapshot's cycle and goes on. bench/reliability.py --crash 20 runs it 20 times."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]


def _bench():
    spec = importlib.util.spec_from_file_location("reliability_bench", REPO / "bench" / "reliability.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["reliability_bench"] = mod
    spec.loader.exec_module(mod)
    return mod


def test_three_random_kills_resume_from_the_last_persisted_cycle(tmp_path):
    rows = _bench().crash(3, seed=11, state=tmp_path, out=lambda *_: None)
    assert len(rows) == 3
    for r in rows:
        assert r["resumed_ok"], r
        assert r["torn_history"] <= 1
    # the session made progress across its lives
    assert rows[-1]["resumed_at"] > rows[0]["resumed_at"] >= 1
