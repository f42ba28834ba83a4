"""The bounded hypothesis queue and the per-cycle selection."""

from __future__ import annotations

import numpy as np
import pytest

from backend.associate import Hypothesis
from backend.config import SelectConfig
from backend.selection import HypothesisQueue, select_spaced


def _hyp(time: float, com) -> Hypothesis:
    return Hypothesis(float(time), np.array([0, 1]), np.zeros((2, 17, 2)), np.full((2, 17), 0.005),
                      np.asarray(com, dtype=np.float64))


def _line(n: int, spacing: float = 1.0, start: int = 0) -> list[Hypothesis]:
    """n hypotheses at times start.., centres ``spacing`` apart along x."""
    return [_hyp(start + i, [spacing * (start + i), 0.0, 1.0]) for i in range(n)]


def test_queue_is_bounded_drops_the_oldest_and_counts():
    q = HypothesisQueue(SelectConfig(queue_size=10, scope=3))
    q.extend(_line(4))
    assert len(q) == 4 and q.dropped == 0 and not q.ready()
    q.extend(_line(21, start=4))
    assert len(q) == 10 and q.dropped == 15
    assert q.ready()  # >= 2 x scope
    taken = q.select(np.random.default_rng(0))
    assert len(taken) == 3 and len(q) == 7
    left = sorted(h.time for h in q._q)
    assert set(left) | {h.time for h in taken} == set(range(15, 25))  # the newest ten
    q.clear()
    assert len(q) == 0 and q.select(np.random.default_rng(0)) == []


def test_selection_respects_min_spacing_scope_and_removes_what_it_takes():
    rng = np.random.default_rng(7)
    q = HypothesisQueue(SelectConfig(scope=20, min_spacing=0.5, queue_size=1000))
    # 300 centres in a 3 m cube: plenty of them closer than 0.5 m to each other
    hyps = [_hyp(i, rng.uniform(0, 3, 3)) for i in range(300)]
    q.extend(hyps)
    taken = q.select(np.random.default_rng(1))
    assert len(taken) == 20
    c = np.array([h.com for h in taken])
    d = np.linalg.norm(c[:, None] - c[None], axis=-1)
    assert d[np.triu_indices(20, 1)].min() >= 0.5
    assert [h.time for h in taken] == sorted(h.time for h in taken)  # returned in queue order
    assert len(q) == 280
    remaining = {id(h) for h in q._q}
    assert not remaining & {id(h) for h in taken}
    # everything close together: the spacing allows only one per cluster
    q2 = HypothesisQueue(SelectConfig(scope=20, min_spacing=0.5))
    q2.extend([_hyp(i, [10.0 * (i % 3), 0.01 * i, 0.0]) for i in range(40)])
    got = q2.select(np.random.default_rng(2))
    assert len(got) == 3 and len(q2) == 37


def test_selection_prefers_newer_hypotheses():
    def mean_rank(bias: float) -> float:
        rng = np.random.default_rng(5)
        ranks = []
        for _ in range(200):
            q = HypothesisQueue(SelectConfig(scope=10, min_spacing=0.0, newer_bias=bias))
            q.extend(_line(100))
            ranks += [h.time / 99 for h in q.select(rng)]
        return float(np.mean(ranks))

    unbiased, biased = mean_rank(0.0), mean_rank(3.0)
    assert unbiased == pytest.approx(0.5, abs=0.03)  # uniform: the mean age rank is 1/2
    assert biased > 0.68  # exp(3 r) weights: ~0.7
    assert biased > unbiased + 0.15


def test_selection_is_deterministic_for_a_seed():
    def pick(seed):
        q = HypothesisQueue(SelectConfig(scope=15, min_spacing=0.3))
        q.extend(_line(100, spacing=0.1))
        return [h.time for h in q.select(np.random.default_rng(seed))]

    assert pick(3) == pick(3)
    assert pick(3) != pick(4)


def test_select_spaced():
    rng = np.random.default_rng(0)
    hyps = [_hyp(i, rng.uniform(0, 2, 3)) for i in range(500)]
    got = select_spaced(hyps, 1000, 0.4, np.random.default_rng(1))
    c = np.array([h.com for h in got])
    d = np.linalg.norm(c[:, None] - c[None], axis=-1)
    assert d[np.triu_indices(len(got), 1)].min() >= 0.4
    assert 20 < len(got) < 200  # far fewer than 500, but the space is filled
    # every hypothesis left out has a taken one within the spacing (greedy is maximal)
    taken = {id(h) for h in got}
    for h in hyps:
        if id(h) not in taken:
            assert np.min(np.linalg.norm(c - h.com, axis=1)) < 0.4
    assert len(select_spaced(hyps, 10, 0.4, np.random.default_rng(1))) == 10
    assert len(select_spaced(hyps, 30, 0.0, np.random.default_rng(1))) == 30
    times = [h.time for h in select_spaced(hyps, 30, 0.0, np.random.default_rng(1))]
    assert times == sorted(times)


def test_select_spaced_fill_takes_the_spaced_first_then_the_rest_up_to_the_budget():
    """A walker passing the same spots again (a corridor): 200 hypotheses at 20 spots.
    Spaced alone keeps one per spot; ``fill`` keeps those and then others up to the budget,
    and all of them when they are fewer."""
    hyps = [_hyp(i, [0.5 * (i % 20), 0.0, 1.0]) for i in range(200)]
    spaced = select_spaced(hyps, 1000, 0.4, np.random.default_rng(1))
    assert len(spaced) == 20
    filled = select_spaced(hyps, 120, 0.4, np.random.default_rng(1), fill=True)
    assert len(filled) == 120 and len({h.com[0] for h in filled}) == 20  # every spot, then more
    assert [h.time for h in filled] == sorted(h.time for h in filled)
    assert len(select_spaced(hyps, 1000, 0.4, np.random.default_rng(1), fill=True)) == 200
