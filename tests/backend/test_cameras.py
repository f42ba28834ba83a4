"""Camera model and camera files: projection and undistortion against OpenCV, the lab's
YAML files, and every broken-file error naming file, line and field."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from backend.cameras import (
    CameraFileError,
    CameraSet,
    Extrinsics,
    Intrinsics,
    Pose,
    dump_extrinsics,
    dump_intrinsics,
    load_extrinsics,
    load_intrinsics,
    parse_extrinsics,
    parse_intrinsics,
    project,
    rays,
    save_extrinsics,
    undistort,
    write_atomic,
)
from backend.geometry import so3_exp

cv2 = pytest.importorskip("cv2")

# Extra coefficients on top of the lab's 4/5-coefficient lenses: rational (k4..k6),
# thin prism (s1..s4) and tilt (tx, ty), of realistic size.
EXTRA = np.array([0.01, -0.004, 0.002, 0.0008, -0.0005, 0.0006, -0.0003, 0.002, -0.0015])


@pytest.fixture(scope="module")
def lab(lab_dir):
    return CameraSet.load(lab_dir / "intrinsics.yaml", lab_dir / "reference.yaml")


def _with_size(intr: Intrinsics, n: int) -> Intrinsics:
    d = np.zeros(14)
    d[: min(len(intr.dist), 5)] = intr.dist[:5]
    d[5:] = EXTRA
    if n == 4:
        return replace(intr, dist=intr.dist[:4].copy())
    if n == 0:
        return replace(intr, dist=np.zeros(0))
    return replace(intr, dist=d[:n].copy())


def _points_in_view(intr: Intrinsics, pose: Pose, rng, n=300, margin=0.02):
    """World points whose projections fall inside the image (to test undistortion where
    it is defined), at 1–10 m depth."""
    w, h = intr.resolution
    uv = np.column_stack([rng.uniform(margin * w, (1 - margin) * w, n), rng.uniform(margin * h, (1 - margin) * h, n)])
    xy = np.column_stack([(uv[:, 0] - intr.cx) / intr.fx, (uv[:, 1] - intr.cy) / intr.fy])  # ~ normalised
    z = rng.uniform(1.0, 10.0, n)
    Xc = np.column_stack([xy * z[:, None], z])
    return pose.to_world(Xc)


def _cv2_project(X, intr: Intrinsics, pose: Pose):
    rvec, _ = cv2.Rodrigues(pose.R.T)
    tvec = -pose.R.T @ pose.t
    dist = intr.dist if len(intr.dist) else None
    uv, _ = cv2.projectPoints(X.reshape(-1, 1, 3), rvec, tvec, intr.K, dist)
    return uv.reshape(-1, 2)


@pytest.mark.parametrize("ncoef", [0, 4, 5, 8, 12, 14])
def test_projection_matches_opencv_on_lab_cameras(lab, ncoef):
    rng = np.random.default_rng(ncoef)
    for name in lab.names:
        intr = _with_size(lab.intrinsics[name], ncoef)
        pose = lab.extrinsics[name].pose
        X = _points_in_view(intr, pose, rng, n=50)
        ours, depth = project(X, intr, pose)
        np.testing.assert_allclose(ours, _cv2_project(X, intr, pose), atol=1e-6, err_msg=f"{name}, {ncoef} coefficients")
        np.testing.assert_allclose(depth, pose.to_camera(X)[:, 2], atol=1e-12)


def test_points_behind_the_camera_project_to_nan(lab):
    intr, pose = lab.intrinsics["cam_5"], lab.extrinsics["cam_5"].pose
    X = pose.to_world(np.array([[0.1, 0.2, -1.0], [0.0, 0.0, 0.0], [0.1, 0.1, 2.0]]))
    uv, z = project(X, intr, pose)
    assert np.all(np.isnan(uv[:2])) and np.all(np.isfinite(uv[2]))
    assert z[0] < 0 and z[2] == pytest.approx(2.0)


@pytest.mark.parametrize("ncoef", [0, 4, 5, 8, 12, 14])
def test_undistortion_inverts_projection(lab, ncoef):
    """Distorted pixels → normalised coordinates equal x/z, y/z of the camera-frame point,
    and agree with OpenCV's own undistortPoints."""
    rng = np.random.default_rng(100 + ncoef)
    for name in lab.names[::3]:
        intr = _with_size(lab.intrinsics[name], ncoef)
        pose = lab.extrinsics[name].pose
        X = _points_in_view(intr, pose, rng, n=100)
        uv, _ = project(X, intr, pose)
        xy = undistort(uv, intr)
        Xc = pose.to_camera(X)
        # 1e-7 normalised ≈ 4e-5 px at f = 430
        np.testing.assert_allclose(xy, Xc[:, :2] / Xc[:, 2:], atol=1e-7, err_msg=f"{name}, {ncoef} coefficients")
        if len(intr.dist):
            crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
            ref = cv2.undistortPointsIter(uv.reshape(-1, 1, 2), intr.K, intr.dist, None, None, crit).reshape(-1, 2) \
                if hasattr(cv2, "undistortPointsIter") else \
                cv2.undistortPoints(uv.reshape(-1, 1, 2), intr.K, intr.dist, None, None, None, crit).reshape(-1, 2)
            np.testing.assert_allclose(xy, ref, atol=1e-9)


def test_undistort_empty_and_rays(lab):
    intr, pose = lab.intrinsics["cam_2"], lab.extrinsics["cam_2"].pose
    assert undistort(np.zeros((0, 2)), intr).shape == (0, 2)
    X = _points_in_view(intr, pose, np.random.default_rng(1), n=20)
    uv, _ = project(X, intr, pose)
    origin, d = rays(uv, intr, pose)
    np.testing.assert_array_equal(origin, pose.t)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    want = (X - pose.t) / np.linalg.norm(X - pose.t, axis=1, keepdims=True)
    np.testing.assert_allclose(d, want, atol=1e-7)


def test_fold_radius_is_where_the_distortion_stops_growing(lab):
    plain = Intrinsics("p", 500.0, 500.0, 320.0, 240.0, np.zeros(0), (640, 480))
    assert plain.fold_radius == np.inf
    # strong barrel fitted to the centre: r(1 + k1 r² + k2 r⁴) peaks at r² = 1.578
    k1 = -0.28
    barrel = replace(plain, dist=np.array([k1, k1 * k1 / 3, 0.0, 0.0, 0.0]))
    assert barrel.fold_radius == pytest.approx(0.7829, abs=2e-4)
    # the model maps two directions (and a third, further out) to one pixel short of the
    # fold; pixels past it have no direction short of the fold at all
    a = 1.0  # tan of the angle off the axis, short of the fold
    rd = a * (1 + k1 * a**2 + k1 * k1 / 3 * a**4)
    b = max(x.real for x in np.roots([k1 * k1 / 3, 0, k1, 0, 1, -rd]) if abs(x.imag) < 1e-9 and 1.3 < x.real < 2.2)
    wide = replace(barrel, fx=250.0, fy=250.0)
    pa, _ = project(np.array([[a, 0.0, 1.0]]), wide, Pose.identity())
    pb, _ = project(np.array([[b, 0.0, 1.0]]), wide, Pose.identity())
    np.testing.assert_allclose(pa, pb, atol=1e-6)
    assert pa[0, 0] < 640 and rd < wide.fold_radius
    # the lab's lenses fold beyond their image corners
    for intr in lab.intrinsics.values():
        w, h = intr.resolution
        corner = max(np.hypot((x - intr.cx) / intr.fx, (y - intr.cy) / intr.fy) for x in (0, w) for y in (0, h))
        assert intr.fold_radius > corner, intr.name


def test_pose_conventions():
    """translation = optical centre, rotation = world_R_cam, OpenCV axes (z = viewing)."""
    R = so3_exp([0.3, -0.2, 0.9])
    pose = Pose(R, np.array([1.0, 2.0, 3.0]))
    # the optical centre maps to the camera origin, a point 2 m ahead lies on +z
    np.testing.assert_allclose(pose.to_camera(pose.t[None]), 0, atol=1e-12)
    ahead = pose.t + 2.0 * R[:, 2]
    np.testing.assert_allclose(pose.to_camera(ahead[None]), [[0, 0, 2.0]], atol=1e-12)
    X = np.random.default_rng(0).normal(size=(5, 3))
    np.testing.assert_allclose(pose.to_world(pose.to_camera(X)), X, atol=1e-12)
    q = pose.quat
    assert q[3] >= 0 and np.isclose(np.linalg.norm(q), 1)
    assert Pose.from_quat(pose.t, q) == pose


def test_intrinsics_scale_to_message_resolution():
    i = Intrinsics("c", 400.0, 410.0, 320.0, 240.0, np.array([0.1, -0.05, 0.0, 0.0]), (640, 480))
    j = i.scaled_to((1280, 960))
    assert (j.fx, j.fy, j.cx, j.cy, j.resolution) == (800.0, 820.0, 640.0, 480.0, (1280, 960))
    np.testing.assert_array_equal(j.dist, i.dist)
    # different ratios: the mean of the two (FORMATS.md)
    k = i.scaled_to((320, 480))
    assert k.fx == pytest.approx(400.0 * 0.75) and k.cy == pytest.approx(240.0 * 0.75)
    assert i.scaled_to((640, 480)) is i


# ---------------------------------------------------------------- lab files


def test_lab_files_load(lab, lab_dir):
    assert len(lab.names) == 20 and lab.names[:3] == ("cam_0", "cam_1", "cam_2") and lab.names[-1] == "cam_19"
    intr = load_intrinsics(lab_dir / "intrinsics.yaml")
    assert {len(i.dist) for i in intr.values()} == {4, 5}
    assert intr["cam_0"].resolution == (848, 480) and intr["cam_4"].resolution == (640, 480)
    ref = load_extrinsics(lab_dir / "reference.yaml")
    assert ref["cam_0"].pose == Pose.identity()
    heights = np.array([e.pose.t for e in ref.values()])
    assert np.ptp(heights, axis=0).max() > 10  # a room of ~240 m², not a toy


def test_lab_extrinsics_yaml_round_trip(lab_dir, tmp_path):
    ref = load_extrinsics(lab_dir / "reference.yaml")
    text = dump_extrinsics(ref, comment="round trip\nof the lab")
    assert text.startswith("# round trip\n# of the lab\n")
    back = parse_extrinsics(text, "<dump>")
    assert list(back) == list(ref)
    for n in ref:
        assert back[n] == ref[n]
        np.testing.assert_allclose(back[n].pose.t, ref[n].pose.t, rtol=0, atol=1e-15)
    save_extrinsics(tmp_path / "out" / "e.yaml", ref, extra={"cam_1": {"std_translation": 0.01, "std_rotation": 0.2}})
    again = load_extrinsics(tmp_path / "out" / "e.yaml")
    assert again["cam_1"].std_translation == 0.01 and again["cam_1"].std_rotation == 0.2
    assert again["cam_2"].std_translation is None and again == ref


def test_lab_intrinsics_yaml_round_trip(lab_dir, tmp_path):
    intr = load_intrinsics(lab_dir / "intrinsics.yaml")
    back = parse_intrinsics(dump_intrinsics(intr), "<dump>")
    assert list(back) == list(intr)
    for n in intr:
        assert back[n] == intr[n]
        np.testing.assert_array_equal(back[n].dist, intr[n].dist)


def test_extra_keys_are_ignored(lab_dir):
    # reference.yaml carries name/topic/origin keys
    assert "topic:" in (lab_dir / "reference.yaml").read_text()
    e = parse_extrinsics("c:\n  translation: [1, 2, 3]\n  rotation: [0, 0, 0, 1]\n  anything: {a: 1}\n")
    assert e["c"].resolution == (0, 0) and np.allclose(e["c"].pose.t, [1, 2, 3])


def test_camera_set_scales_intrinsics_to_extrinsics_resolution(lab_dir):
    intr = load_intrinsics(lab_dir / "intrinsics.yaml")
    ext = load_extrinsics(lab_dir / "reference.yaml")
    ext["cam_0"] = replace(ext["cam_0"], resolution=(424, 240))
    cs = CameraSet.combine(intr, ext)
    assert cs.intrinsics["cam_0"].fx == pytest.approx(intr["cam_0"].fx / 2)
    assert cs.intrinsics["cam_1"].fx == intr["cam_1"].fx


def test_camera_sets_that_differ_are_named(lab_dir):
    intr = load_intrinsics(lab_dir / "intrinsics.yaml")
    ext = load_extrinsics(lab_dir / "reference.yaml")
    del ext["cam_7"]
    ext["cam_99"] = ext["cam_1"]
    del intr["cam_12"]
    with pytest.raises(CameraFileError) as e:
        CameraSet.combine(intr, ext, "I.yaml", "E.yaml")
    msg = str(e.value)
    assert "camera sets differ" in msg and "in the intrinsics only: cam_7" in msg
    assert "in the extrinsics only: cam_12, cam_99" in msg and msg.startswith("E.yaml")


# ---------------------------------------------------------------- broken files

GOOD_I = """cam_0:
  intrinsics: [400, 400, 320, 240]
  distortion_coeffs: [0.1, -0.05, 0.0, 0.0, 0.01]
  resolution: [640, 480]
cam_1:
  intrinsics: [410, 410, 330, 250]
  distortion_coeffs: [0.1, -0.05, 0.0, 0.0]
  resolution: [640, 480]
"""

GOOD_E = """cam_0:
  translation: [0, 0, 0]
  rotation: [0, 0, 0, 1]
  resolution: [640, 480]
cam_1:
  translation: [1.5, 0.2, -0.3]
  rotation: [0, 0.7071068, 0, 0.7071068]
  resolution: [640, 480]
"""

BROKEN_I = [
    # (replace this, by that, line, field, reason fragment)
    ("intrinsics: [410, 410, 330, 250]", "intrinsics: [410, 410, 330]", 6, "cam_1.intrinsics", "expected 4 numbers, got 3 values"),
    ("intrinsics: [410, 410, 330, 250]", "intrinsics: [410, x, 330, 250]", 6, "cam_1.intrinsics", "element 1 is 'x', not a finite number"),
    ("intrinsics: [410, 410, 330, 250]", "intrinsics: [410, .nan, 330, 250]", 6, "cam_1.intrinsics", "element 1 is nan"),
    ("intrinsics: [410, 410, 330, 250]", "intrinsics: [-410, 410, 330, 250]", 6, "cam_1.intrinsics", "focal lengths must be positive"),
    ("intrinsics: [410, 410, 330, 250]", "intrinsics: 410", 6, "cam_1.intrinsics", "expected 4 numbers, got int"),
    ("  intrinsics: [410, 410, 330, 250]\n", "", 5, "cam_1", "missing 'intrinsics'"),
    ("distortion_coeffs: [0.1, -0.05, 0.0, 0.0]", "distortion_coeffs: [0.1, -0.05, 0.0]", 7, "cam_1.distortion_coeffs", "expected 0 or 4 or 5 or 8 or 12 or 14 numbers, got 3 values"),
    ("resolution: [640, 480]\n", "resolution: [640.5, 480]\n", 4, "cam_0.resolution", "positive integer width and height"),
    ("  resolution: [640, 480]\ncam_1", "cam_1", 1, "cam_0", "missing 'resolution'"),
]


def _write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.mark.parametrize("old,new,line,field,reason", BROKEN_I, ids=[b[4][:30] for b in BROKEN_I])
def test_broken_intrinsics_name_file_line_field(tmp_path, old, new, line, field, reason):
    assert old in GOOD_I
    p = _write(tmp_path, "intrinsics.yaml", GOOD_I.replace(old, new, 1))
    with pytest.raises(CameraFileError) as e:
        load_intrinsics(p)
    assert (e.value.source, e.value.line, e.value.field) == (str(p), line, field)
    assert reason in e.value.reason
    assert str(e.value).startswith(f"{p}:{line}: {field}: ")


BROKEN_E = [
    ("rotation: [0, 0.7071068, 0, 0.7071068]", "rotation: [0, 0.7, 0, 0.7]", 7, "cam_1.rotation", "must be unit length, norm is 0.989949"),
    ("rotation: [0, 0.7071068, 0, 0.7071068]", "rotation: [0, 0, 1]", 7, "cam_1.rotation", "expected 4 numbers, got 3 values"),
    ("translation: [1.5, 0.2, -0.3]", "translation: [1.5, .inf, -0.3]", 6, "cam_1.translation", "element 1 is inf"),
    ("translation: [1.5, 0.2, -0.3]", "translation: [1.5, true, -0.3]", 6, "cam_1.translation", "element 1 is True"),
    ("  translation: [1.5, 0.2, -0.3]\n", "", 5, "cam_1", "missing 'translation'"),
    ("resolution: [640, 480]\ncam_1", "resolution: [0, 480]\ncam_1", 4, "cam_0.resolution", "positive integer"),
]


@pytest.mark.parametrize("old,new,line,field,reason", BROKEN_E, ids=[b[4][:30] for b in BROKEN_E])
def test_broken_extrinsics_name_file_line_field(tmp_path, old, new, line, field, reason):
    assert old in GOOD_E
    p = _write(tmp_path, "extrinsics.yaml", GOOD_E.replace(old, new, 1))
    with pytest.raises(CameraFileError) as e:
        load_extrinsics(p)
    assert (e.value.source, e.value.line, e.value.field) == (str(p), line, field)
    assert reason in e.value.reason


@pytest.mark.parametrize("text,line,reason", [
    ("cam_0:\n  translation: [0, 0, 0\n  rotation: [0, 0, 0, 1]\n", 3, "not valid YAML"),
    ("cam_0:\n\ttranslation: [0, 0, 0]\n", 2, "not valid YAML"),
    ("", None, "file is empty"),
    ("# only a comment\n", None, "file is empty"),
    ("- cam_0\n- cam_1\n", 1, "expected a mapping of camera names"),
])
def test_unparsable_files(tmp_path, text, line, reason):
    p = _write(tmp_path, "e.yaml", text)
    with pytest.raises(CameraFileError) as e:
        load_extrinsics(p)
    assert e.value.source == str(p) and e.value.line == line and reason in e.value.reason


def test_camera_entry_that_is_not_a_mapping(tmp_path):
    p = _write(tmp_path, "e.yaml", GOOD_E + "cam_2: [1, 2, 3]\n")
    with pytest.raises(CameraFileError) as e:
        load_extrinsics(p)
    assert (e.value.line, e.value.field) == (9, "cam_2") and "expected a mapping" in e.value.reason


def test_missing_file(tmp_path):
    with pytest.raises(CameraFileError, match="intrinsics file does not exist"):
        load_intrinsics(tmp_path / "nope.yaml")
    with pytest.raises(CameraFileError, match="extrinsics file does not exist"):
        load_extrinsics(tmp_path / "nope.yaml")


def test_write_atomic_replaces_whole_file(tmp_path):
    p = tmp_path / "a" / "b.yaml"
    write_atomic(p, "one\n")
    write_atomic(p, b"two\n")
    assert p.read_text() == "two\n"
    assert [x.name for x in p.parent.iterdir()] == ["b.yaml"]  # no temporary left behind


def test_extrinsics_equality_ignores_std():
    e = Extrinsics(Pose.identity(), (640, 480), 0.1, 1.0)
    assert e == Extrinsics(Pose.identity(), (640, 480))
    assert e != Extrinsics(Pose(np.eye(3), np.array([0, 0, 1e-3])), (640, 480))
