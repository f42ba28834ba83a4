"""Accuracy figures (FORMATS.md): rigid, shape (similarity) and scale."""

from __future__ import annotations

import json

import numpy as np
import pytest

from backend.cameras import Pose, load_extrinsics
from backend.evaluate import evaluate
from backend.geometry import rotation_angle_deg, so3_exp


@pytest.fixture(scope="module")
def ref(lab_dir) -> dict[str, Pose]:
    return {k: v.pose for k, v in load_extrinsics(lab_dir / "reference.yaml").items()}


def _transform(poses, s, R, t):
    """The same rig in another frame and scale: X' = s R X + t."""
    return {k: Pose(R @ p.R, s * R @ p.t + t) for k, p in poses.items()}


def test_reference_against_itself_is_zero(ref):
    acc = evaluate(ref, ref)
    assert len(acc.cameras) == 20 and acc.cameras[:3] == ("cam_0", "cam_1", "cam_2")
    for st in (acc.position, acc.orientation, acc.shape_position, acc.shape_orientation):
        assert st.max == pytest.approx(0, abs=1e-6) and st.mean == pytest.approx(0, abs=1e-6)
    assert acc.scale == pytest.approx(1.0, abs=1e-12)


def test_rigid_transform_of_the_reference_is_zero(ref):
    acc = evaluate(_transform(ref, 1.0, so3_exp([0.3, -0.7, 1.9]), np.array([5.0, -3.0, 2.0])), ref)
    assert acc.position.max < 1e-9 and acc.orientation.max < 1e-5
    assert acc.scale == pytest.approx(1.0, abs=1e-12)


def test_similarity_transform_has_zero_shape_error_and_the_right_scale(ref):
    s = 1.08
    res = _transform(ref, s, so3_exp([-0.2, 0.5, 0.1]), np.array([1.0, 2.0, 3.0]))
    acc = evaluate(res, ref)
    assert acc.shape_position.max < 1e-9 and acc.shape_orientation.max < 1e-5
    assert acc.scale == pytest.approx(1 / s, rel=1e-12)  # the factor that maps the result onto the reference
    # rigid figures see the scale: each centre is off by |s - 1| times its distance from the centroid
    C = np.array([ref[n].t for n in acc.cameras])
    want = (s - 1) * np.linalg.norm(C - C.mean(0), axis=1)
    got = np.array([acc.per_camera[n][0] for n in acc.cameras])
    np.testing.assert_allclose(got, want, atol=1e-9)
    assert acc.orientation.max < 1e-5  # a scale does not turn the cameras


def test_single_camera_rotation_offset_is_that_error(ref):
    res = dict(ref)
    res["cam_7"] = Pose(so3_exp(np.radians(3.0) * np.array([0, 0.6, 0.8])) @ ref["cam_7"].R, ref["cam_7"].t)
    acc = evaluate(res, ref)
    assert acc.per_camera["cam_7"][1] == pytest.approx(3.0, abs=1e-9)
    assert acc.per_camera["cam_7"][3] == pytest.approx(3.0, abs=1e-9)
    assert max(v[1] for k, v in acc.per_camera.items() if k != "cam_7") < 1e-5
    assert acc.orientation.max == pytest.approx(3.0) and acc.orientation.mean == pytest.approx(3.0 / 20)
    assert acc.position.max < 1e-9


def test_single_camera_position_offset(ref):
    """A camera moved by d: the alignment spreads a little of it over the others; the
    figures equal an independent least-squares alignment and the moved camera keeps most."""
    opt = pytest.importorskip("scipy.optimize")
    d = np.array([0.3, -0.2, 0.1])
    res = dict(ref)
    res["cam_12"] = Pose(ref["cam_12"].R, ref["cam_12"].t + d)
    acc = evaluate(res, ref)
    names = acc.cameras
    src = np.array([res[n].t for n in names])
    dst = np.array([ref[n].t for n in names])
    fit = opt.minimize(lambda x: np.sum((src @ so3_exp(x[:3]).T + x[3:] - dst) ** 2), np.zeros(6), method="BFGS",
                       options={"gtol": 1e-12})
    want = np.linalg.norm(src @ so3_exp(fit.x[:3]).T + fit.x[3:] - dst, axis=1)
    got = np.array([acc.per_camera[n][0] for n in names])
    np.testing.assert_allclose(got, want, atol=1e-5)
    k = names.index("cam_12")
    assert 0.85 * np.linalg.norm(d) < got[k] <= np.linalg.norm(d) + 1e-9
    assert np.delete(got, k).max() < 0.1 * np.linalg.norm(d)


def test_per_camera_rotation_error_after_alignment(ref):
    """A result in another frame: orientation errors use the alignment rotation."""
    R = so3_exp([0.1, 0.2, 0.3])
    res = _transform(ref, 1.0, R, np.zeros(3))
    res["cam_3"] = Pose(so3_exp([0.02, 0, 0]) @ res["cam_3"].R, res["cam_3"].t)
    acc = evaluate(res, ref)
    assert acc.per_camera["cam_3"][1] == pytest.approx(np.degrees(0.02), abs=1e-6)
    assert rotation_angle_deg(res["cam_3"].R, ref["cam_3"].R) > 10  # the raw angle is not the figure


def test_subset_missing_and_too_few(ref):
    acc = evaluate(ref, ref, cameras=["cam_0", "cam_5", "cam_9"])
    assert acc.cameras == ("cam_0", "cam_5", "cam_9")
    with pytest.raises(ValueError, match="cameras missing from result or reference: cam_42"):
        evaluate(ref, ref, cameras=["cam_0", "cam_1", "cam_42"])
    with pytest.raises(ValueError, match="need at least 2 cameras in common"):
        evaluate({k: ref[k] for k in ("cam_0",)}, ref)
    # only the common cameras count
    part = {k: v for k, v in ref.items() if k not in ("cam_4", "cam_8")}
    assert len(evaluate(part, ref).cameras) == 18


def test_report_forms(ref):
    res = dict(ref)
    res["cam_1"] = Pose(ref["cam_1"].R, ref["cam_1"].t + [0.05, 0, 0])
    acc = evaluate(res, ref)
    d = json.loads(json.dumps(acc.to_dict()))
    assert set(d["per_camera"]["cam_1"]) == {"position", "orientation", "shape_position", "shape_orientation"}
    assert d["position"]["max"] == pytest.approx(acc.position.max)
    s = acc.summary()
    assert s.startswith(f"position {acc.position.mean:.4f} m") and "scale" in s


@pytest.mark.parametrize("names", [("cam_0", "cam_7"), ("cam_0", "cam_7", "LINE")])
def test_two_cameras_or_a_line_are_aligned_by_their_orientations_too(ref, names):
    """Two centres (or centres on one line) leave any turn about their line free; the
    orientations fix it, so a similarity of the rig is no error and a camera turned
    about the baseline is."""
    rig = {n: ref[n] for n in names if n != "LINE"}
    if "LINE" in names:  # a third camera on the line through the first two
        a, b = rig["cam_0"], rig["cam_7"]
        rig["LINE"] = Pose(ref["cam_3"].R, a.t + 0.4 * (b.t - a.t))
    R, t = so3_exp([0.4, -1.1, 0.3]), np.array([2.0, 1.0, -0.5])
    moved = _transform(rig, 1.05, R, t)
    acc = evaluate(moved, rig)
    assert acc.shape_position.max < 1e-9 and acc.shape_orientation.max < 1e-6
    assert acc.scale == pytest.approx(1 / 1.05, rel=1e-9)
    # cam_7 turned 1° about the baseline: centres alone would take it for the frame's turn
    b = rig["cam_7"].t - rig["cam_0"].t
    turned = dict(rig)
    turned["cam_7"] = Pose(so3_exp(np.radians(1.0) * b / np.linalg.norm(b)) @ rig["cam_7"].R, rig["cam_7"].t)
    acc = evaluate(turned, rig)
    # the mean orientation fixes the frame: the turned camera keeps (N-1)/N of its 1°
    assert acc.orientation.max == pytest.approx(1 - 1 / len(rig), abs=0.01)
    assert acc.position.max < 1e-9


def test_the_tilt_of_a_result_s_up_is_measured_through_any_frame_and_scale(ref):
    from backend.evaluate import up_tilt

    up = np.array([-0.006, 0.830, -0.557])  # the lab's floor normal (room.yaml)
    up /= np.linalg.norm(up)
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(up, z)  # the turn that takes the floor's up to z: a level result's frame
    level = so3_exp(v / np.linalg.norm(v) * np.arccos(up @ z))
    # and then 3° about the result's x: its z stands 3° from up
    for tilt in (0.0, 3.0):
        res = _transform(ref, 0.9, so3_exp([np.radians(tilt), 0.0, 0.0]) @ level, np.array([1.0, 2.0, 3.0]))
        assert up_tilt(res, ref, up) == pytest.approx(tilt, abs=1e-6)
    assert np.isnan(up_tilt({n: ref[n] for n in ("cam_0", "cam_1")}, ref, up))
