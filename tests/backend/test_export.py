"""Every export format read back with its ecosystem's reader; poses must come back to 1e-9."""

from __future__ import annotations

import io
import json
import re
import tomllib
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest
import typer
import yaml
from typer.testing import CliRunner

from backend.cameras import (Extrinsics, Intrinsics, Pose, load_extrinsics, load_intrinsics,
                             parse_extrinsics, project)
from backend.export import FORMATS, ExportError, colmap_files, export, export_warnings
from backend.geometry import quat_to_R, so3_exp

TOL = 1e-9


@pytest.fixture(scope="module")
def lab(lab_dir: Path):
    return load_extrinsics(lab_dir / "reference.yaml"), load_intrinsics(lab_dir / "intrinsics.yaml")


@pytest.fixture(scope="module")
def mixed():
    """Cameras with 0, 4, 5 and 8 distortion coefficients and awkward names, random poses."""
    rng = np.random.default_rng(7)
    dists = {"cam_0": [], "cam_2": [0.01, -0.02, 0.001, 0.002], "cam_10": [-0.05, 0.06, 0.0002, -0.0007, -0.02],
             "left-1": [-0.05, 0.06, 0.0002, -0.0007, -0.02, 0.001, 0.002, 0.003]}
    ext, intr = {}, {}
    for k, (name, d) in enumerate(dists.items()):
        R = so3_exp(rng.normal(size=3) * 1.5)
        t = rng.normal(size=3) * 4
        ext[name] = Extrinsics(Pose(R, t), (640 + 64 * k, 480), 0.01 * k, 0.1 * k)
        intr[name] = Intrinsics(name, 500.0 + k, 501.5 + k, 320.25 + k, 240.5, np.array(d, float), (640 + 64 * k, 480))
    return ext, intr


def _assert_pose(R, t, e: Extrinsics, what: str):
    assert np.abs(R - e.pose.R).max() < TOL, f"{what}: rotation differs"
    assert np.abs(t - e.pose.t).max() < TOL, f"{what}: position differs"


def _world_points(e: Extrinsics) -> np.ndarray:
    """Points in front of the camera, in the world."""
    rng = np.random.default_rng(1)
    Xc = np.column_stack([rng.uniform(-1, 1, 5), rng.uniform(-0.7, 0.7, 5), rng.uniform(2, 6, 5)])
    return e.pose.to_world(Xc)


def test_formats_and_media_types(lab):
    ext, intr = lab
    assert set(FORMATS) == {"ais", "json", "opencv", "pose2sim", "kalibr", "colmap"}
    for fmt, media in FORMATS.items():
        body, mt = export(ext, intr, fmt)
        assert mt == media
        assert isinstance(body, bytes if fmt == "colmap" else str) and len(body) > 100


def test_ais_round_trip(mixed):
    ext, intr = mixed
    body, _ = export(ext, {}, "ais")
    back = parse_extrinsics(body)
    assert list(back) == ["cam_0", "cam_2", "cam_10", "left-1"]  # natural order
    for n, e in ext.items():
        _assert_pose(back[n].pose.R, back[n].pose.t, e, n)
        assert back[n].std_translation == pytest.approx(e.std_translation)


def test_json_round_trip(mixed):
    ext, intr = mixed
    doc = json.loads(export(ext, intr, "json")[0])
    assert doc["format"] == "extrcal.calibration" and doc["version"] == 1
    for n, e in ext.items():
        c = doc["cameras"][n]
        _assert_pose(quat_to_R(c["rotation"]), np.array(c["translation"]), e, n)
        Rwc, twc = np.array(c["cam_R_world"]), np.array(c["cam_t_world"])
        _assert_pose(Rwc.T, -Rwc.T @ twc, e, n)
        assert c["intrinsics"]["distortion_coeffs"] == list(intr[n].dist)
    # Without intrinsics json still works, and says nothing about them.
    doc = json.loads(export(ext, {}, "json")[0])
    assert "intrinsics" not in doc["cameras"]["cam_0"]


@pytest.mark.parametrize("which", ["lab", "mixed"])
def test_opencv_filestorage(which, request, tmp_path):
    ext, intr = request.getfixturevalue(which)
    path = tmp_path / "calib.yaml"
    path.write_text(export(ext, intr, "opencv")[0])
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.isOpened()
    node_names = [fs.getNode("cameras").at(k).string() for k in range(fs.getNode("cameras").size())]
    assert len(node_names) == len(ext)
    for node_name in node_names:
        node = fs.getNode(node_name)
        name = node.getNode("name").string()
        e, i = ext[name], intr[name]
        K, D, R, t = (node.getNode(k).mat() for k in ("K", "D", "R", "t"))
        assert R.shape == (3, 3) and t.shape == (3, 1)
        # R, t are world→camera: the optical centre is -Rᵀt
        _assert_pose(R.T, (-R.T @ t).ravel(), e, name)
        assert np.array_equal(K, i.K)
        assert (int(node.getNode("image_width").real()), int(node.getNode("image_height").real())) == i.resolution
        if len(i.dist):
            assert np.array_equal(D.ravel(), i.dist)
        else:
            assert not np.any(D)
        # OpenCV's own projection with these numbers lands where ours does.
        X = _world_points(e)
        uv_cv, _ = cv2.projectPoints(X, cv2.Rodrigues(R)[0], t, K, D)
        uv, _ = project(X, i, e.pose)
        assert np.abs(uv_cv.reshape(-1, 2) - uv).max() < 1e-6
    fs.release()


@pytest.mark.parametrize("which", ["lab", "mixed"])
def test_pose2sim_toml(which, request):
    ext, intr = request.getfixturevalue(which)
    doc = tomllib.loads(export(ext, intr, "pose2sim")[0])
    assert doc["metadata"] == {"adjusted": False, "error": 0.0}
    cams = [k for k in doc if k != "metadata"]
    assert cams == list(sorted(ext, key=lambda n: [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", n)]))
    for key in cams:
        c = doc[key]
        e, i = ext[c["name"]], intr[c["name"]]
        assert c["fisheye"] is False
        assert c["size"] == [float(i.resolution[0]), float(i.resolution[1])]
        K = np.array(c["matrix"])
        assert np.array_equal(K, i.K)
        # Pose2Sim reads rotation with cv2.Rodrigues and builds P = K [R | T] (world→camera).
        R = cv2.Rodrigues(np.array(c["rotation"]))[0]
        T = np.array(c["translation"])
        _assert_pose(R.T, -R.T @ T, e, key)
        D = np.array(c["distortions"])
        if len(i.dist) > 4 and np.any(i.dist[4:]):
            assert np.array_equal(D, i.dist)
        else:
            assert len(D) == 4 and np.array_equal(D, np.pad(i.dist, (0, 4))[:4])
        X = _world_points(e)
        uv_cv, _ = cv2.projectPoints(X, np.array(c["rotation"]), T, K, D)
        assert np.abs(uv_cv.reshape(-1, 2) - project(X, i, e.pose)[0]).max() < 1e-6


@pytest.mark.parametrize("which", ["lab", "mixed"])
def test_kalibr_camchain_composes_back(which, request):
    ext, intr = request.getfixturevalue(which)
    text = export(ext, intr, "kalibr")[0]
    doc = yaml.safe_load(text)
    keys = list(doc)
    assert keys == [f"cam{k}" for k in range(len(ext))]
    assert all("T_cam_imu" not in doc[k] for k in keys)
    assert "T_cn_cnm1" not in doc["cam0"]
    # cam0's world pose is stated in the header; compose the chain from it.
    e0 = ext[doc["cam0"]["camera_name"]]
    T_w_c = np.eye(4)
    T_w_c[:3, :3], T_w_c[:3, 3] = e0.pose.R, e0.pose.t
    for k in keys:
        c = doc[k]
        assert c["camera_model"] == "pinhole" and c["distortion_model"] == "radtan"
        name = c["camera_name"]
        i = intr[name]
        assert c["intrinsics"] == [i.fx, i.fy, i.cx, i.cy]
        assert c["resolution"] == list(i.resolution)
        assert c["distortion_coeffs"] == list(np.pad(i.dist, (0, 4))[:4])
        if k != "cam0":
            T = np.array(c["T_cn_cnm1"])
            assert T.shape == (4, 4) and np.array_equal(T[3], [0, 0, 0, 1])
            T_w_c = T_w_c @ np.linalg.inv(T)
        # the chain accumulates rounding; 1e-9 still holds over 20 cameras
        _assert_pose(T_w_c[:3, :3], T_w_c[:3, 3], ext[name], k)
    # k3 is dropped and said so, with the pixel cost.
    dropped = [n for n, i in intr.items() if len(i.dist) > 4 and np.any(i.dist[4:])]
    warnings = export_warnings(ext, intr, "kalibr")
    assert len(warnings) == len(dropped) and all(w.split(":")[0] in dropped for w in warnings)
    for w in warnings:
        assert f"# {w}" in text
        assert float(re.search(r"by ([0-9.]+) px", w).group(1)) > 0.1


def parse_colmap_text(files: dict[str, str]) -> tuple[dict, dict]:
    """A parser written from COLMAP's documented text format (doc/format.rst)."""
    nparams = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8,
               "FULL_OPENCV": 12}
    cameras = {}
    for line in files["cameras.txt"].splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        f = line.split()
        cid, model, w, h = int(f[0]), f[1], int(f[2]), int(f[3])
        params = [float(x) for x in f[4:]]
        assert len(params) == nparams[model], line
        cameras[cid] = (model, w, h, params)
    images = {}
    lines = files["images.txt"].splitlines()
    data = [ln for ln in lines if not ln.startswith("#")]
    # two lines per image: the pose line, then the (here empty) 2D points line
    assert len(data) % 2 == 0
    for pose_line, points_line in zip(data[::2], data[1::2]):
        f = pose_line.split()
        assert len(f) == 10 and points_line.strip() == ""
        qw, qx, qy, qz, tx, ty, tz = map(float, f[1:8])
        images[f[9]] = (int(f[0]), np.array([qx, qy, qz, qw]), np.array([tx, ty, tz]), int(f[8]))
    assert all(ln.startswith("#") or not ln.strip() for ln in files["points3D.txt"].splitlines())
    return cameras, images


@pytest.mark.parametrize("which", ["lab", "mixed"])
def test_colmap_zip(which, request):
    ext, intr = request.getfixturevalue(which)
    body, media = export(ext, intr, "colmap")
    assert media == "application/zip"
    with zipfile.ZipFile(io.BytesIO(body)) as z:
        assert sorted(z.namelist()) == ["cameras.txt", "images.txt", "points3D.txt"]
        files = {n: z.read(n).decode() for n in z.namelist()}
    assert files == colmap_files(ext, intr)
    assert export(ext, intr, "colmap")[0] == body  # reproducible bytes
    cameras, images = parse_colmap_text(files)
    assert set(images) == set(ext)
    for name, (iid, q, t, cid) in images.items():
        R = quat_to_R(q)  # world→camera
        _assert_pose(R.T, -R.T @ t, ext[name], name)
        model, w, h, params = cameras[cid]
        i = intr[name]
        assert (w, h) == i.resolution and params[:4] == [i.fx, i.fy, i.cx, i.cy]
        d = np.pad(i.dist, (0, 8))
        want = "PINHOLE" if not np.any(d) else "OPENCV" if not np.any(d[4:]) else "FULL_OPENCV"
        assert model == want
        assert np.array_equal(params[4:], d[: len(params) - 4])


def test_colmap_with_pycolmap(mixed, tmp_path):
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap (the test extra) is not installed")
    ext, intr = mixed
    for n, text in colmap_files(ext, intr).items():
        (tmp_path / n).write_text(text)
    rec = pycolmap.Reconstruction(str(tmp_path))
    assert rec.num_images() == len(ext) and rec.num_points3D() == 0
    for img in rec.images.values():
        e, i = ext[img.name], intr[img.name]
        M = np.asarray(img.cam_from_world().matrix() if callable(img.cam_from_world) else img.cam_from_world.matrix())
        R, t = M[:, :3], M[:, 3]
        # pycolmap keeps float64 quaternions; 1e-9 holds through its normalisation
        _assert_pose(R.T, -R.T @ t, e, img.name)
        assert np.abs(np.asarray(img.projection_center()) - e.pose.t).max() < TOL
        cam = rec.cameras[img.camera_id]
        assert (cam.width, cam.height) == i.resolution
        # COLMAP's own projection (with its distortion model) agrees with ours.
        X = _world_points(e)
        uv_ours, _ = project(X, i, e.pose)
        for Xk, uk in zip(X, uv_ours):
            uv = np.asarray(cam.img_from_cam(R @ Xk + t)).ravel()[:2]
            assert np.abs(uv - uk).max() < 1e-6


def test_errors(mixed):
    ext, intr = mixed
    with pytest.raises(ExportError, match="unknown export format 'fbx'"):
        export(ext, intr, "fbx")
    for fmt in ("opencv", "pose2sim", "kalibr", "colmap"):
        with pytest.raises(ExportError, match=f"the {fmt} format needs intrinsics; none for cam_0"):
            export(ext, {k: v for k, v in intr.items() if k != "cam_0"}, fmt)
    with pytest.raises(ExportError, match="no cameras"):
        export({}, {}, "ais")
    tilted = dict(intr)
    tilted["cam_0"] = Intrinsics("cam_0", 500, 500, 320, 240, np.r_[np.zeros(12), 0.01, 0.0], (640, 480))
    with pytest.raises(ExportError, match="cam_0: thin-prism/tilt"):
        export(ext, tilted, "colmap")
    bad = dict(ext)
    bad["cam_0"] = Extrinsics(Pose(np.eye(3), np.array([np.nan, 0, 0])), (640, 480))
    with pytest.raises(ExportError, match="cam_0: the pose is not finite"):
        export(bad, intr, "json")
    meta = {"metadata": ext["cam_0"]}
    with pytest.raises(ExportError, match="collides"):
        export(meta, {"metadata": intr["cam_0"]}, "pose2sim")


@pytest.fixture()
def cli():
    from backend.cli_tools import register

    app = typer.Typer()
    register(app)
    app.command("noop")(lambda: None)  # keep typer from collapsing to a single command
    return app


def test_cli_export(cli, lab_dir, tmp_path):
    runner = CliRunner()
    ref, intr = str(lab_dir / "reference.yaml"), str(lab_dir / "intrinsics.yaml")
    r = runner.invoke(cli, ["export", ref, "--intrinsics", intr, "--format", "pose2sim",
                            "--out", str(tmp_path / "Calib.toml")])
    assert r.exit_code == 0, r.output
    assert tomllib.loads((tmp_path / "Calib.toml").read_text())["cam_19"]["fisheye"] is False
    r = runner.invoke(cli, ["export", ref, "--intrinsics", intr, "--format", "kalibr",
                            "--out", str(tmp_path / "camchain.yaml")])
    assert r.exit_code == 0 and "warning: cam_0: radtan keeps" in r.output
    r = runner.invoke(cli, ["export", ref, "--intrinsics", intr, "--format", "colmap", "--out", str(tmp_path / "m")])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (tmp_path / "m").iterdir()) == ["cameras.txt", "images.txt", "points3D.txt"]
    r = runner.invoke(cli, ["export", ref, "--intrinsics", intr, "--format", "colmap", "--out", str(tmp_path / "m.zip")])
    assert r.exit_code == 0 and zipfile.is_zipfile(tmp_path / "m.zip")
    r = runner.invoke(cli, ["export", ref, "--format", "json"])
    assert r.exit_code == 0 and json.loads(r.stdout)["cameras"]["cam_3"]["resolution"] == [848, 480]
    # clear errors
    r = runner.invoke(cli, ["export", ref, "--format", "opencv"])
    assert r.exit_code == 2 and "needs intrinsics" in r.output
    r = runner.invoke(cli, ["export", ref, "--format", "nope"])
    assert r.exit_code == 2 and "unknown format 'nope'" in r.output
    broken = tmp_path / "broken.yaml"
    broken.write_text("cam_0:\n  translation: [0, 0]\n  rotation: [0, 0, 0, 1]\n")
    r = runner.invoke(cli, ["export", str(broken)])
    assert r.exit_code == 2 and "broken.yaml:2: cam_0.translation" in r.output
    r = runner.invoke(cli, ["export", ref, "--intrinsics", intr, "--format", "colmap"])
    assert r.exit_code == 2 and "binary" in r.output
