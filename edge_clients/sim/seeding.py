"""Independent, reproducible random streams, one per purpose.

A stream is keyed by (seed, purpose, ...), e.g. (0, "walker", 1) or (0, "detector",
"cam_3"): the same key gives the same numbers in every process and on every platform,
and no stream's use shifts another's (no global random state).
"""

from __future__ import annotations

import hashlib

import numpy as np


def rng_for(seed: int, *key: object) -> np.random.Generator:
    digest = hashlib.sha256(repr((int(seed),) + tuple(str(k) for k in key)).encode()).digest()
    words = np.frombuffer(digest, dtype="<u4")
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(w) for w in words])))
