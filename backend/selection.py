"""The bounded hypothesis queue and the selection of one cycle's hypotheses.

Selection is a random permutation biased to newer hypotheses, taking each one that is
at least ``min_spacing`` from those already taken, until ``scope`` are taken. Taken
hypotheses leave the queue: each measurement enters the filter once, so the filter's
covariance stays honest.
"""

from __future__ import annotations

from collections import deque
from typing import Callable

import numpy as np

from .associate import Hypothesis
from .config import SelectConfig


class HypothesisQueue:
    def __init__(self, config: SelectConfig):
        self.cfg = config
        self._q: deque[Hypothesis] = deque()
        self.dropped = 0
        self.first_time = float("inf")  # data time of the first hypothesis ever queued

    def __len__(self) -> int:
        return len(self._q)

    def extend(self, hyps: list[Hypothesis]) -> None:
        for h in hyps:
            self.first_time = min(self.first_time, h.time)
            if len(self._q) >= self.cfg.queue_size:
                self._q.popleft()  # oldest first: the newest data describes the scene now
                self.dropped += 1
            self._q.append(h)

    def newest(self, n: int) -> list[Hypothesis]:
        """The last ``n`` hypotheses queued, oldest first (the queue is left as it is)."""
        return list(self._q)[-n:] if n > 0 else []

    def clear(self) -> None:
        self._q.clear()

    def ready(self) -> bool:
        return len(self._q) >= 2 * self.cfg.scope

    def spread(self, min_views: int) -> int:
        """How many queued hypotheses with at least ``min_views`` views are min_spacing
        apart: what a selection could take."""
        hyps = [h for h in self._q if len(h.cams) >= min_views]
        return len(select_spaced(hyps, len(hyps), self.cfg.min_spacing, np.random.default_rng(0)))

    def select(self, rng: np.random.Generator, scope: int | None = None,
               usable: Callable[[Hypothesis], bool] | None = None) -> list[Hypothesis]:
        """Up to ``scope`` (default the config's) hypotheses, taken out of the queue; only
        ``usable`` ones are taken, the others stay for later cycles."""
        scope = scope or self.cfg.scope
        n = len(self._q)
        if n == 0:
            return []
        age_rank = np.arange(n) / max(n - 1, 1)  # 0 = oldest, 1 = newest
        w = np.exp(self.cfg.newer_bias * age_rank)
        # Efraimidis-Spirakis: weighted random permutation via keys u^(1/w).
        keys = rng.random(n) ** (1.0 / w)
        order = np.argsort(-keys)
        items = list(self._q)
        taken: list[int] = []
        coms = np.zeros((0, 3))
        min_sq = self.cfg.min_spacing**2
        for i in order:
            if usable is not None and not usable(items[i]):
                continue
            c = items[i].com
            if len(coms) and np.min(((coms - c) ** 2).sum(1)) < min_sq:
                continue
            taken.append(int(i))
            coms = np.vstack([coms, c])
            if len(taken) >= scope:
                break
        keep = np.ones(n, bool)
        keep[taken] = False
        self._q = deque(h for h, k in zip(items, keep) if k)
        return [items[i] for i in sorted(taken)]


def select_spaced(hyps: list[Hypothesis], n: int, spacing: float, rng: np.random.Generator, *,
                  fill: bool = False) -> list[Hypothesis]:
    """Up to n hypotheses in random order, each >= spacing from those taken (grid hash);
    ``fill``: then the others, in random order, until n are taken (spacing decides what a
    budget keeps first, it does not throw data away below the budget)."""
    if spacing <= 0 or (fill and len(hyps) <= n):
        order = rng.permutation(len(hyps))[:n]
        return [hyps[i] for i in sorted(order)]
    cells: dict[tuple[int, int, int], list[np.ndarray]] = {}
    taken = []
    sq = spacing * spacing
    for i in rng.permutation(len(hyps)):
        c = hyps[i].com
        k = tuple(np.floor(c / spacing).astype(int))
        near = False
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for dz in (-1, 0, 1):
                    for o in cells.get((k[0] + dx, k[1] + dy, k[2] + dz), ()):
                        if ((o - c) ** 2).sum() < sq:
                            near = True
                            break
        if near:
            continue
        cells.setdefault(k, []).append(c)
        taken.append(int(i))
        if len(taken) >= n:
            break
    if fill and len(taken) < n:
        rest = np.setdiff1d(np.arange(len(hyps)), taken)
        taken.extend(rng.permutation(rest)[:n - len(taken)].tolist())
    return [hyps[i] for i in sorted(taken)]
