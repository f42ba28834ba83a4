"""A calibration in the file formats of the tools our users have.

``export(extrinsics, intrinsics, fmt) -> (body, media type)``; the CLI (`extrcal export`)
and the service (`GET /sessions/{id}/result?format=F`) both call it.

Conventions. Our extrinsics are camera poses in the world (FORMATS.md): ``R = world_R_cam``,
``t`` = optical centre. Most tools want the opposite direction, the world→camera transform
of OpenCV's ``x_cam = R_wc · X_world + t_wc``, i.e. ``R_wc = Rᵀ`` and ``t_wc = -Rᵀ t``.
Each writer below says which one it writes. Intrinsics are written as given in the
intrinsics file (at that file's resolution): a pose does not depend on the resolution.

Formats (``FORMATS``):

- ``ais``: the native extrinsics YAML (FORMATS.md), text. Needs no intrinsics.
- ``json``: the same content as JSON (``extrcal.calibration`` v1), with intrinsics when given
  and both pose directions spelled out.
- ``opencv``: an OpenCV FileStorage YAML (``cv2.FileStorage`` reads it): per camera
  ``K`` 3×3, ``D`` 1×N (OpenCV order), ``R`` 3×3 and ``t`` 3×1 **world→camera** (OpenCV's
  convention, what ``cv2.projectPoints``/``solvePnP`` use), plus ``image_width``/
  ``image_height`` and the camera's ``name``; a top-level ``cameras`` list names the nodes.
  Node names that FileStorage cannot take (it allows ``[A-Za-z0-9_-]``, first a letter or
  ``_``) are sanitised; ``name`` keeps the original.
- ``pose2sim``: a Pose2Sim ``Calib.toml``: one ``[<camera>]`` table each with ``name``,
  ``size`` [w, h], ``matrix`` K, ``distortions``, ``rotation`` (Rodrigues vector) and
  ``translation``, both world→camera, ``fisheye = false``; and ``[metadata]``. Pose2Sim
  hands ``distortions`` to OpenCV, so we write (k1, k2, p1, p2) when every further coefficient
  is zero (Pose2Sim's own layout) and the full OpenCV vector otherwise.
- ``kalibr``: a kalibr camchain YAML: ``cam0``, ``cam1``… in natural camera order, each with
  ``camera_model: pinhole``, ``intrinsics [fu, fv, pu, pv]``, ``distortion_model: radtan``,
  ``distortion_coeffs [k1, k2, p1, p2]``, ``resolution``, ``rostopic`` (``/<name>/image_raw``),
  ``camera_name`` (ours) and, from ``cam1`` on, ``T_cn_cnm1``: the 4×4 transform taking
  points from the previous camera's frame into this one's (``X_cn = T_cn_cnm1 · X_cnm1``).
  The chain is relative, so the world frame is that of ``cam0``: compose the chain and
  apply ``cam0``'s world pose (in the header comment, and in the ``json`` export) to get
  world poses back. No IMU: ``T_cam_imu`` and ``timeshift_cam_imu`` are absent.
  radtan has four coefficients: **k3 and any further coefficients are dropped**; the file's
  header comment says so per camera with how far that moves the image corner (pixels), and
  ``export_warnings`` returns the same lines for the CLI to print.
- ``colmap``: a COLMAP text model in a **zip** (``application/zip``) holding
  ``cameras.txt`` (one camera per sensor: ``PINHOLE`` without distortion, ``OPENCV`` for
  k1, k2, p1, p2, ``FULL_OPENCV`` when k3…k6 are used; thin-prism and tilt terms cannot be
  expressed and are an error), ``images.txt`` (one image per camera named after the camera,
  ``QW QX QY QZ TX TY TZ`` world→camera, Hamilton quaternion, and an empty 2D-point line)
  and an empty ``points3D.txt``. ``colmap_files`` gives the three texts as a dict.
"""

from __future__ import annotations

import io
import json
import math
import re
import zipfile
from typing import Callable, Mapping

import numpy as np

from .cameras import Extrinsics, Intrinsics, dump_extrinsics, natural_key
from .geometry import R_to_quat, so3_log

FORMATS: dict[str, str] = {
    "ais": "application/yaml",
    "json": "application/json",
    "opencv": "application/yaml",
    "pose2sim": "application/toml",
    "kalibr": "application/yaml",
    "colmap": "application/zip",
}

# Suggested file names, for the CLI's default --out and the service's Content-Disposition.
FILENAMES: dict[str, str] = {
    "ais": "extrinsics.yaml",
    "json": "calibration.json",
    "opencv": "calibration_opencv.yaml",
    "pose2sim": "Calib.toml",
    "kalibr": "camchain.yaml",
    "colmap": "colmap_model.zip",
}


class ExportError(ValueError):
    """A calibration that cannot be written in the asked format; the message says why."""


def export(extrinsics: Mapping[str, Extrinsics], intrinsics: Mapping[str, Intrinsics],
           fmt: str) -> tuple[str | bytes, str]:
    """The calibration in format ``fmt`` (one of ``FORMATS``): (body, media type).

    ``intrinsics`` may be empty for ``ais`` and ``json``; the other formats need every
    camera's intrinsics.
    """
    if fmt not in FORMATS:
        raise ExportError(f"unknown export format {fmt!r}; choose one of {', '.join(FORMATS)}")
    _check_poses(extrinsics)
    return _WRITERS[fmt](extrinsics, intrinsics), FORMATS[fmt]


def export_warnings(extrinsics: Mapping[str, Extrinsics], intrinsics: Mapping[str, Intrinsics],
                    fmt: str) -> list[str]:
    """What the format loses for these cameras (one line each), empty when nothing."""
    if fmt != "kalibr":
        return []
    out = []
    for name in _names(extrinsics):
        i = intrinsics.get(name)
        if i is not None and len(i.dist) > 4 and np.any(i.dist[4:]):
            out.append(f"{name}: radtan keeps k1, k2, p1, p2; dropping "
                       f"{_fmt_list(i.dist[4:])} moves the image corner by "
                       f"{_corner_shift_px(i):.2f} px")
    return out


# ------------------------------------------------------------------ helpers


def _names(extrinsics: Mapping[str, Extrinsics]) -> list[str]:
    return sorted(extrinsics, key=natural_key)


def _check_poses(extrinsics: Mapping[str, Extrinsics]) -> None:
    if not extrinsics:
        raise ExportError("the calibration has no cameras")
    for name, e in extrinsics.items():
        if not (np.all(np.isfinite(e.pose.R)) and np.all(np.isfinite(e.pose.t))):
            raise ExportError(f"{name}: the pose is not finite")


def _need_intrinsics(extrinsics: Mapping[str, Extrinsics], intrinsics: Mapping[str, Intrinsics],
                     fmt: str) -> None:
    missing = [n for n in _names(extrinsics) if n not in intrinsics]
    if missing:
        raise ExportError(f"the {fmt} format needs intrinsics; none for {', '.join(missing)}")


def world_to_camera(e: Extrinsics) -> tuple[np.ndarray, np.ndarray]:
    """(R_wc (3, 3), t_wc (3,)) with x_cam = R_wc · X_world + t_wc (OpenCV's extrinsics)."""
    R = e.pose.R.T
    return R, -R @ e.pose.t


def _num(x: float) -> str:
    """A float that reads back bit-exactly (repr is the shortest round-trip form)."""
    x = float(x)
    if not math.isfinite(x):
        raise ExportError(f"cannot write the non-finite number {x}")
    return repr(x)


def _fmt_list(v) -> str:
    return "[" + ", ".join(_num(x) for x in v) + "]"


def _dist5(i: Intrinsics) -> np.ndarray:
    d = np.zeros(14)
    d[: len(i.dist)] = i.dist
    return d


def _corner_shift_px(i: Intrinsics) -> float:
    """Pixels the image corner moves when only k1, k2, p1, p2 of ``i`` are kept."""
    from .cameras import distort, normalized_to_pixels, undistort

    w, h = i.resolution
    corners = np.array([[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]])
    xy = undistort(corners, i)
    full = normalized_to_pixels(distort(xy, i.dist), i)
    cut = normalized_to_pixels(distort(xy, i.dist[:4]), i)
    return float(np.max(np.linalg.norm(full - cut, axis=1)))


# ------------------------------------------------------------------ writers


def _ais(extrinsics, intrinsics) -> str:
    return dump_extrinsics({n: extrinsics[n] for n in _names(extrinsics)})


def _json(extrinsics, intrinsics) -> str:
    cams = {}
    for n in _names(extrinsics):
        e = extrinsics[n]
        Rwc, twc = world_to_camera(e)
        d: dict = {
            "translation": e.pose.t.tolist(),
            "rotation": R_to_quat(e.pose.R).tolist(),
            "world_R_cam": e.pose.R.tolist(),
            "cam_R_world": Rwc.tolist(),
            "cam_t_world": twc.tolist(),
            "resolution": [int(e.resolution[0]), int(e.resolution[1])],
            "std_translation": e.std_translation,
            "std_rotation": e.std_rotation,
        }
        if n in intrinsics:
            i = intrinsics[n]
            d["intrinsics"] = {
                "fx": i.fx, "fy": i.fy, "cx": i.cx, "cy": i.cy, "K": i.K.tolist(),
                "distortion_coeffs": [float(x) for x in i.dist],
                "resolution": [int(i.resolution[0]), int(i.resolution[1])],
            }
        cams[n] = d
    doc = {
        "format": "extrcal.calibration",
        "version": 1,
        "convention": (
            "translation = optical centre in the world (m), rotation = world_R_cam quaternion "
            "[x, y, z, w], OpenCV camera axes; cam_R_world/cam_t_world map world points into "
            "the camera: x_cam = cam_R_world @ X + cam_t_world"
        ),
        "cameras": cams,
    }
    return json.dumps(doc, indent=2) + "\n"


_CV_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_-]*$")


def opencv_node_names(names: list[str]) -> dict[str, str]:
    """Camera name → FileStorage node name (unique, [A-Za-z_][A-Za-z0-9_-]*)."""
    out: dict[str, str] = {}
    used: set[str] = set()
    for n in names:
        s = n if _CV_NAME.match(n) else "_" + re.sub(r"[^A-Za-z0-9_-]", "_", n)
        base, k = s, 1
        while s in used or s == "cameras":
            k += 1
            s = f"{base}_{k}"
        used.add(s)
        out[n] = s
    return out


def _cv_matrix(name: str, M: np.ndarray, indent: str) -> str:
    M = np.atleast_2d(np.asarray(M, dtype=np.float64))
    data = ", ".join(_num(x) for x in M.ravel())
    return (f"{indent}{name}: !!opencv-matrix\n{indent}   rows: {M.shape[0]}\n"
            f"{indent}   cols: {M.shape[1]}\n{indent}   dt: d\n{indent}   data: [ {data} ]\n")


def _opencv(extrinsics, intrinsics) -> str:
    _need_intrinsics(extrinsics, intrinsics, "opencv")
    names = _names(extrinsics)
    nodes = opencv_node_names(names)
    parts = [
        "%YAML:1.0\n---\n",
        # FileStorage's YAML takes no comments before the first node; this string is read
        # back by cv2 and documents the convention inside the file.
        'convention: "R, t map world points into the camera (OpenCV): x_cam = R X + t; '
        'the optical centre is -R^T t"\n',
        "cameras: [ " + ", ".join(json.dumps(nodes[n]) for n in names) + " ]\n",
    ]
    for n in names:
        i = intrinsics[n]
        Rwc, twc = world_to_camera(extrinsics[n])
        parts.append(f"{nodes[n]}:\n")
        parts.append(f"   name: {json.dumps(n)}\n")
        parts.append(f"   image_width: {int(i.resolution[0])}\n   image_height: {int(i.resolution[1])}\n")
        parts.append(_cv_matrix("K", i.K, "   "))
        if len(i.dist):
            parts.append(_cv_matrix("D", i.dist.reshape(1, -1), "   "))
        else:  # FileStorage cannot hold a 1x0 matrix; five zeros are "no distortion"
            parts.append(_cv_matrix("D", np.zeros((1, 5)), "   "))
        parts.append(_cv_matrix("R", Rwc, "   "))
        parts.append(_cv_matrix("t", twc.reshape(3, 1), "   "))
    return "".join(parts)


_TOML_BARE = re.compile(r"^[A-Za-z0-9_-]+$")


def _toml_key(k: str) -> str:
    return k if _TOML_BARE.match(k) else json.dumps(k)


def _pose2sim(extrinsics, intrinsics) -> str:
    _need_intrinsics(extrinsics, intrinsics, "pose2sim")
    names = _names(extrinsics)
    if "metadata" in names:
        raise ExportError("a camera named 'metadata' collides with Pose2Sim's [metadata] table")
    out = []
    for n in names:
        i = intrinsics[n]
        Rwc, twc = world_to_camera(extrinsics[n])
        d = i.dist if len(i.dist) > 4 and np.any(i.dist[4:]) else _dist5(i)[:4]
        K = i.K
        out.append(
            f"[{_toml_key(n)}]\n"
            f"name = {json.dumps(n)}\n"
            f"size = [ {_num(i.resolution[0])}, {_num(i.resolution[1])},]\n"
            f"matrix = [ " + " ".join(f"[ {', '.join(_num(x) for x in row)},]," for row in K) + "]\n"
            f"distortions = [ {', '.join(_num(x) for x in d)},]\n"
            f"rotation = [ {', '.join(_num(x) for x in so3_log(Rwc))},]\n"
            f"translation = [ {', '.join(_num(x) for x in twc)},]\n"
            f"fisheye = false\n\n"
        )
    out.append("[metadata]\nadjusted = false\nerror = 0.0\n")
    return "".join(out)


def _kalibr(extrinsics, intrinsics) -> str:
    _need_intrinsics(extrinsics, intrinsics, "kalibr")
    names = _names(extrinsics)
    e0 = extrinsics[names[0]]
    head = [
        "# kalibr camchain written by extrcal.",
        "# T_cn_cnm1 maps points from cam(n-1)'s frame into cam(n)'s: X_cn = T_cn_cnm1 X_cnm1.",
        f"# World pose of cam0 ({names[0]}): translation {_fmt_list(e0.pose.t)}, "
        f"rotation world_R_cam [x, y, z, w] {_fmt_list(R_to_quat(e0.pose.R))}.",
        "# No IMU: T_cam_imu and timeshift_cam_imu are absent.",
    ]
    head += [f"# {w}" for w in export_warnings(extrinsics, intrinsics, "kalibr")]
    lines = head
    prev = None
    for k, n in enumerate(names):
        i = intrinsics[n]
        e = extrinsics[n]
        lines.append(f"cam{k}:")
        lines.append(f"  camera_name: {json.dumps(n)}")
        lines.append("  camera_model: pinhole")
        lines.append(f"  intrinsics: {_fmt_list([i.fx, i.fy, i.cx, i.cy])}")
        lines.append("  distortion_model: radtan")
        lines.append(f"  distortion_coeffs: {_fmt_list(_dist5(i)[:4])}")
        lines.append(f"  resolution: [{int(i.resolution[0])}, {int(i.resolution[1])}]")
        lines.append(f"  rostopic: {json.dumps('/' + n + '/image_raw')}")
        if prev is not None:
            # T_cn_cnm1 = T_cn_w · T_w_cnm1
            R = e.pose.R.T @ prev.pose.R
            t = e.pose.R.T @ (prev.pose.t - e.pose.t)
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, t
            lines.append("  T_cn_cnm1:")
            lines += [f"  - {_fmt_list(row)}" for row in T]
        prev = e
    return "\n".join(lines) + "\n"


def colmap_files(extrinsics: Mapping[str, Extrinsics],
                 intrinsics: Mapping[str, Intrinsics]) -> dict[str, str]:
    """COLMAP's text model: {'cameras.txt', 'images.txt', 'points3D.txt'} → text."""
    _check_poses(extrinsics)
    _need_intrinsics(extrinsics, intrinsics, "colmap")
    names = _names(extrinsics)
    cams = ["# Camera list with one line of data per camera:",
            "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
            f"# Number of cameras: {len(names)}"]
    imgs = ["# Image list with two lines of data per image:",
            "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
            "#   POINTS2D[] as (X, Y, POINT3D_ID)",
            f"# Number of images: {len(names)}, mean observations per image: 0"]
    for k, n in enumerate(names, start=1):
        if re.search(r"\s", n):
            raise ExportError(f"{n!r}: COLMAP image names cannot contain white space")
        i = intrinsics[n]
        d = _dist5(i)
        if np.any(d[8:]):
            raise ExportError(f"{n}: thin-prism/tilt distortion terms have no COLMAP camera model")
        if not np.any(d):
            model, params = "PINHOLE", [i.fx, i.fy, i.cx, i.cy]
        elif not np.any(d[4:]):
            model, params = "OPENCV", [i.fx, i.fy, i.cx, i.cy, *d[:4]]
        else:
            model, params = "FULL_OPENCV", [i.fx, i.fy, i.cx, i.cy, *d[:8]]
        cams.append(f"{k} {model} {int(i.resolution[0])} {int(i.resolution[1])} "
                    + " ".join(_num(x) for x in params))
        Rwc, twc = world_to_camera(extrinsics[n])
        qx, qy, qz, qw = R_to_quat(Rwc)
        imgs.append(f"{k} " + " ".join(_num(x) for x in (qw, qx, qy, qz, *twc)) + f" {k} {n}")
        imgs.append("")
    pts = ["# 3D point list with one line of data per point:",
           "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
           "# Number of points: 0, mean track length: 0"]
    return {"cameras.txt": "\n".join(cams) + "\n", "images.txt": "\n".join(imgs) + "\n",
            "points3D.txt": "\n".join(pts) + "\n"}


def _colmap(extrinsics, intrinsics) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for name, text in colmap_files(extrinsics, intrinsics).items():
            info = zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))  # reproducible bytes
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            z.writestr(info, text)
    return buf.getvalue()


_WRITERS: dict[str, Callable[..., str | bytes]] = {
    "ais": _ais, "json": _json, "opencv": _opencv, "pose2sim": _pose2sim,
    "kalibr": _kalibr, "colmap": _colmap,
}
