"""Faults for the optimizer, run in the service's real worker process (picklable by
reference: the worker imports this module). ``EXTRCAL_TEST_SOLVER_FAULTS`` names a file
with one fault per line, taken in order, one per cycle; when it is empty the real
``optimize.solve`` runs.

- ``raise``: the solve raises in the worker (GTSAM's indeterminant-system error text);
- ``degenerate``: the real solve on degenerate geometry (every camera moved to one point,
  looking one way: no ray pair meets at an angle, no landmark can be placed);
- ``crash``: the worker process dies (``os._exit``).
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from backend.optimize import Problem, solve


def degenerate(p: Problem) -> Problem:
    C = len(p.R)
    R = np.repeat(p.R[:1], C, axis=0)
    t = np.repeat(p.t[:1], C, axis=0)
    return replace(p, R=R, t=t, prior_R=R.copy(), prior_t=t.copy())


def faulty_solve(p: Problem):
    plan = Path(os.environ["EXTRCAL_TEST_SOLVER_FAULTS"])
    lines = plan.read_text().split() if plan.exists() else []
    if not lines:
        return solve(p)
    plan.write_text("".join(f"{x}\n" for x in lines[1:]))
    what = lines[0]
    if what == "raise":
        raise RuntimeError("Indeterminant linear system detected while working near variable x1 (injected)")
    if what == "degenerate":
        return solve(degenerate(p))
    if what == "crash":
        os._exit(3)
    raise ValueError(f"unknown fault {what!r} in {plan}")
