"""The state's small reports."""

from __future__ import annotations

import numpy as np

from backend.cameras import Intrinsics
from backend.state import Lenses


def test_lenses_in_pixels_and_as_intrinsics():
    names = ["a", "b", "c"]
    lenses = np.array([[0.01, 0.012, 0.002, -0.004], [np.nan] * 4, [-0.02, -0.02, 0.0, 0.001]])
    files = {n: Intrinsics(n, 600.0, 500.0, 320.0, 240.0, np.zeros(5), (640, 480)) for n in names}
    focal = np.array([(files[n].fx, files[n].fy) for n in names])
    got = Lenses.of(names, lenses, np.array([0.015, 0.015, 0.003, 0.003]), focal)
    assert set(got.cameras) == {"a", "c"}  # b was not in the solve
    assert np.allclose(got.cameras["a"], (0.01, 0.012, 1.2, -2.0))  # the shift in px: fx, fy times it
    assert got.spread_focal == 0.015 and np.isclose(got.spread_centre_px, 0.003 * 550.0)
    out = got.intrinsics(files)
    assert out["b"] == files["b"]
    a = out["a"]
    assert np.allclose([a.fx, a.fy, a.cx, a.cy], [606.0, 506.0, 321.2, 238.0])
    assert "1.50 % in focal length" in got.summary() and "c focal -2.00 % / -2.00 %" in got.summary()
    assert "a principal point (+1.2, -2.0) px" in got.summary()
    assert got.to_dict()["cameras"]["c"]["fx"] == -0.02
    # a group the data showed no spread in is not named
    focal_only = Lenses({"a": (0.01, 0.01, 0.0, 0.0)}, 0.01, 0.0).summary()
    assert "1.00 % in focal length across" in focal_only and "principal point" not in focal_only
