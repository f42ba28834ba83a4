"""Initial estimates with exactly the requested perturbation (the paper's protocol)."""

from __future__ import annotations

import numpy as np
import pytest

from backend.cameras import load_extrinsics
from backend.geometry import rotation_angle_deg
from backend.perturb import perturb_extrinsics


@pytest.fixture(scope="module")
def ref(lab_dir):
    return load_extrinsics(lab_dir / "reference.yaml")


@pytest.mark.parametrize("translation,rotation", [(0.25, 10.0), (0.75, 20.0), (0.0, 5.0), (0.1, 0.0)])
def test_exact_magnitudes_all_but_the_first(ref, translation, rotation):
    out = perturb_extrinsics(ref, translation, rotation, seed=3)
    assert list(out) == list(ref)
    assert out["cam_0"] == ref["cam_0"]
    dirs = []
    for n in list(ref)[1:]:
        dt = out[n].pose.t - ref[n].pose.t
        assert np.linalg.norm(dt) == pytest.approx(translation, abs=1e-12)
        assert rotation_angle_deg(out[n].pose.R, ref[n].pose.R) == pytest.approx(rotation, abs=1e-6)
        assert out[n].resolution == ref[n].resolution
        if translation:
            dirs.append(dt / translation)
    if dirs:  # random directions, not one shared offset
        assert np.linalg.norm(np.mean(dirs, axis=0)) < 0.6


def test_seeded(ref):
    a = perturb_extrinsics(ref, 0.25, 10, seed=1)
    b = perturb_extrinsics(ref, 0.25, 10, seed=1)
    c = perturb_extrinsics(ref, 0.25, 10, seed=2)
    assert all(a[n] == b[n] for n in ref)
    assert not all(a[n] == c[n] for n in ref)


def test_keep_first_false_moves_every_camera(ref):
    out = perturb_extrinsics(ref, 0.25, 10, seed=0, keep_first=False)
    for n in ref:
        assert np.linalg.norm(out[n].pose.t - ref[n].pose.t) == pytest.approx(0.25)


def test_std_fields_are_cleared(ref):
    from dataclasses import replace

    with_std = {n: replace(e, std_translation=0.1, std_rotation=1.0) for n, e in ref.items()}
    out = perturb_extrinsics(with_std, 0.25, 10, seed=0)
    assert all(e.std_translation is None and e.std_rotation is None for e in out.values())
