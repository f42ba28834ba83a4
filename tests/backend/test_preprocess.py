"""Preprocessing: the paper's filters, undistortion with the lab's real lenses, sigma."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from backend.cameras import Intrinsics, Pose, load_intrinsics, project
from backend.config import PreprocessConfig
from backend.preprocess import JOINT_NOISE, TORSO, Preprocessor, duplicates
from backend.sync import Frameset, View


@pytest.fixture(scope="module")
def lab_intrinsics(lab_dir):
    return load_intrinsics(lab_dir / "intrinsics.yaml")


@pytest.fixture(scope="module")
def pre(lab_intrinsics):
    names = ("cam_0", "cam_4")  # 848x480 with 5 coefficients, 640x480 with 4
    return lambda cfg=PreprocessConfig(): Preprocessor(cfg, names, {n: lab_intrinsics[n] for n in names})


def _body(centre, height=1.8) -> np.ndarray:
    """(17, 3) joints of an upright person in a camera frame (y down), facing the camera."""
    h = height
    x = {0: (0, -0.93), 1: (0.03, -0.95), 2: (-0.03, -0.95), 3: (0.07, -0.94), 4: (-0.07, -0.94),
         5: (0.0877, -0.818), 6: (-0.0877, -0.818), 7: (0.12, -0.63), 8: (-0.12, -0.63),
         9: (0.13, -0.47), 10: (-0.13, -0.47), 11: (0.0763, -0.526), 12: (-0.0763, -0.526),
         13: (0.08, -0.28), 14: (-0.08, -0.28), 15: (0.08, -0.04), 16: (-0.08, -0.04)}
    J = np.array([[x[j][0] * h, (x[j][1] + 0.5) * h, 0.0] for j in range(17)])
    return J + np.asarray(centre, dtype=np.float64)


def _view(sensor, persons_uv, size, *, conf=0.9, boxes=None, cov=None, offset=0.0, speed=None, seq=5):
    kp = np.stack([np.c_[uv, np.full(17, conf) if np.isscalar(conf) else conf] for uv in persons_uv]) \
        if persons_uv else np.zeros((0, 17, 3))
    P = len(kp)
    b = np.full((P, 4), np.nan) if boxes is None else np.asarray(boxes, dtype=np.float64)
    sp = np.zeros((P, 17)) if speed is None else speed
    return View(sensor, 100.0 + offset, offset, size, kp, b, cov, sp, offset == 0.0, seq, np.arange(P))


def _pixels(intr, J):
    uv, z = project(J, intr, Pose.identity())
    assert np.all(z > 0)
    return uv


def test_undistorted_xy_is_the_normalised_projection(pre, lab_intrinsics):
    p = pre()
    rng = np.random.default_rng(0)
    for cam in ("cam_0", "cam_4"):
        intr = lab_intrinsics[cam]
        W, H = intr.resolution
        for _ in range(20):
            # anywhere in the image, including its distorted edges
            while True:
                c = [rng.uniform(-2.5, 2.5), rng.uniform(-1.0, 1.0), rng.uniform(2.5, 6.0)]
                J = _body(c)
                uv = _pixels(intr, J)
                if np.all((uv > 2) & (uv < [W - 2, H - 2])):
                    break
            dets = p.view(_view(cam, [uv], (W, H)))
            assert len(dets) == 1
            want = J[:, :2] / J[:, 2:]
            assert np.abs(dets[0].xy - want).max() < 1e-9
            assert dets[0].cam == ("cam_0", "cam_4").index(cam)
            assert dets[0].focal == pytest.approx(0.5 * (intr.fx + intr.fy))
    # distortion is not negligible: raw normalised pixels would be off
    intr = lab_intrinsics["cam_0"]
    J = _body([2.2, 0.0, 3.0])
    raw = (_pixels(intr, J) - [intr.cx, intr.cy]) / [intr.fx, intr.fy]
    assert np.abs(raw - J[:, :2] / J[:, 2:]).max() * intr.fx > 3  # px


def test_a_message_at_another_resolution_with_the_same_aspect_is_scaled(pre, lab_intrinsics):
    p = pre()
    intr = lab_intrinsics["cam_0"]  # 848x480
    J = _body([1.5, 0.1, 3.5])
    uv = _pixels(intr, J) * 0.5  # the sensor sent 424x240 images' pixels
    dets = p.view(_view("cam_0", [uv], (424, 240)))
    assert len(dets) == 1
    assert np.abs(dets[0].xy - J[:, :2] / J[:, 2:]).max() < 1e-9
    assert dets[0].focal == pytest.approx(0.25 * (intr.fx + intr.fy))
    # another aspect ratio cannot be the same camera: rejected, counted per person
    assert p.view(_view("cam_0", [uv, uv + 300], (640, 480))) == []
    assert p.rejected["resolution_mismatch"] == 2


def test_confidence_threshold_drops_joints_and_a_person_needs_a_shoulder_and_a_hip(pre, lab_intrinsics):
    p = pre(PreprocessConfig(partial_torso=True))
    intr = lab_intrinsics["cam_4"]
    uv = _pixels(intr, _body([0.0, 0.0, 4.0]))
    conf = np.full(17, 0.9)
    conf[9], conf[10], conf[0] = 0.59, 0.0, 0.6  # wrists below, nose at the threshold (kept)
    [d] = p.view(_view("cam_4", [uv], intr.resolution, conf=conf))
    assert np.all(np.isnan(d.xy[[9, 10]])) and np.all(np.isnan(d.sigma[[9, 10]]))
    keep = np.setdiff1d(np.arange(17), [9, 10])
    assert np.all(np.isfinite(d.xy[keep])) and np.all(np.isfinite(d.sigma[keep]))
    # one side hidden (a profile view): kept, the hidden joints missing
    c = np.full(17, 0.9)
    c[[6, 12]] = 0.3
    [d] = p.view(_view("cam_4", [uv], intr.resolution, conf=c))
    assert np.all(np.isnan(d.xy[[6, 12]])) and np.all(np.isfinite(d.xy[[5, 11]]))
    # no shoulder, or no hip: nobody the association can place
    for gone in ([5, 6], [11, 12], [5, 6, 11]):
        c = np.full(17, 0.9)
        c[gone] = 0.5
        assert p.view(_view("cam_4", [uv], intr.resolution, conf=c)) == []
    assert p.rejected["no_torso"] == 3
    assert p.accepted == 2


def test_as_the_paper_a_missing_torso_joint_drops_the_person(pre, lab_intrinsics):
    p = pre(PreprocessConfig(partial_torso=False))
    intr = lab_intrinsics["cam_4"]
    uv = _pixels(intr, _body([0.0, 0.0, 4.0]))
    for j in TORSO:
        c = np.full(17, 0.9)
        c[j] = 0.5
        assert p.view(_view("cam_4", [uv], intr.resolution, conf=c)) == []
    assert p.rejected["no_torso"] == 4 and p.accepted == 0


def test_a_sensor_whose_torso_confidences_run_below_the_threshold_is_warned_about(pre, lab_intrinsics):
    """Half its persons seen badly (the detector's clearly seen joints still score
    high): no rescaling, most dropped, a warning."""
    p = pre()
    intr = lab_intrinsics["cam_4"]
    uv = _pixels(intr, _body([0.0, 0.0, 4.0]))
    low = np.full(17, 0.45)
    ok = np.full(17, 0.95)
    ok0 = ok.copy()
    ok0[[5, 11]] = 0.0  # one side of the torso not detected: missing, not low
    for i in range(100):
        p.view(_view("cam_4", [uv], intr.resolution, conf=ok if i % 5 < 2 else low))  # 60 % low
        p.view(_view("cam_0", [_pixels(lab_intrinsics["cam_0"], _body([0.0, 0.0, 4.0]))],
                     lab_intrinsics["cam_0"].resolution, conf=ok0))
    rep = p.confidence_report()
    assert rep["cam_4"]["torso_keypoints"] == 400 and rep["cam_4"]["below_confidence"] == 0.6
    assert rep["cam_4"]["confidence_scale"] == 1.0
    assert "below preprocess.min_confidence (0.6)" in rep["cam_4"]["warning"]
    assert rep["cam_0"]["torso_keypoints"] == 200 and rep["cam_0"]["below_confidence"] == 0.0
    assert rep["cam_0"]["warning"] is None
    assert pre().confidence_report() == {}


@pytest.mark.parametrize("level, factor, kept", [(0.45, 2.0, True), (0.15, 3.0, False)])
def test_a_detector_whose_confidences_run_lower_is_scaled_to_the_threshold_s_scale(pre, lab_intrinsics, level,
                                                                                   factor, kept):
    """Every joint at ``level``: after 200 torso joints its confidences are scaled so
    that their 90th percentile is confidence_reference (0.9), at most x3."""
    p = pre()
    intr = lab_intrinsics["cam_4"]
    uv = _pixels(intr, _body([0.0, 0.0, 4.0]))
    conf = np.full(17, level)
    got = [p.view(_view("cam_4", [uv], intr.resolution, conf=conf)) for _ in range(60)]
    assert got[:49] == [[]] * 49  # 196 torso joints: not yet
    assert all(bool(g) == kept for g in got[49:])
    rep = p.confidence_report()["cam_4"]
    assert rep["confidence_scale"] == pytest.approx(factor, rel=0.02)
    # a sensor that has sent too little yet takes all sensors' factor
    assert p.confidence.factor("cam_0") == p.confidence.factor("cam_4")
    if kept:  # the noise model sees the scaled confidence too
        assert np.allclose(got[-1][0].sigma, PreprocessConfig().pixel_sigma * JOINT_NOISE / min(1.0, level * factor),
                           rtol=0.02)
    else:
        assert "its confidences scaled x3.00" in rep["warning"]
    # off: taken as they are
    q = pre(PreprocessConfig(confidence_reference=None))
    assert not any(q.view(_view("cam_4", [uv], intr.resolution, conf=conf)) for _ in range(60))


def test_joints_outside_the_image_are_dropped_and_a_wrong_size_is_warned_about(pre, lab_intrinsics):
    p = pre()
    intr = lab_intrinsics["cam_4"]
    W, H = intr.resolution
    uv = _pixels(intr, _body([0.0, 0.0, 4.0]))
    guessed = uv.copy()
    guessed[15] = [uv[15, 0], H + 30.0]  # an ankle guessed below the border, confidently
    guessed[9] = [-40.0, uv[9, 1]]  # a wrist left of it
    guessed[16] = [uv[16, 0], H + 0.5]  # on the border by a pixel-centre convention: kept
    [d] = p.view(_view("cam_4", [guessed], intr.resolution))
    assert np.all(np.isnan(d.xy[[9, 15]])) and np.all(np.isnan(d.sigma[[9, 15]]))
    assert np.all(np.isfinite(d.xy[16]))
    # both hips outside: the person has no torso to place
    cut = uv.copy()
    cut[[11, 12], 1] = H + 5.0
    assert p.view(_view("cam_4", [cut], intr.resolution)) == []
    assert p.rejected["no_torso"] == 1
    rep = p.confidence_report()
    assert rep["cam_4"]["outside_image"] == pytest.approx(4 / 34, abs=1e-4)
    assert rep["cam_4"]["warning"] is None  # too few joints to judge, and few outside

    # a sensor that reports half its keypoints' resolution: most joints lie outside
    q = pre()
    big = uv * 2.0
    for _ in range(20):
        q.view(_view("cam_4", [big], intr.resolution))
    rep = q.confidence_report()["cam_4"]
    assert rep["outside_image"] > 0.2
    assert "outside its images' size" in rep["warning"]

def test_joints_where_the_lens_model_folds_back_are_dropped():
    k1 = -0.28  # fitted to the centre: folds at a distorted radius of 0.783, 196 px at f = 250
    intr = Intrinsics("cam_w", 250.0, 250.0, 320.0, 240.0, np.array([k1, k1 * k1 / 3, 0.0, 0.0, 0.0]), (640, 480))
    p = Preprocessor(PreprocessConfig(), ("cam_w",), {"cam_w": intr})
    uv = _pixels(intr, _body([0.0, 0.0, 4.0]))
    assert np.all(np.hypot(uv[:, 0] - 320, uv[:, 1] - 240) < 150)
    far = uv.copy()
    far[9] = [320 + 230.0, 240.0]  # a wrist 230 px out: inside the image, past the fold
    [d] = p.view(_view("cam_w", [far], intr.resolution))
    assert np.all(np.isnan(d.xy[9])) and np.isfinite(d.xy[[j for j in range(17) if j != 9]]).all()
    rep = p.confidence_report()["cam_w"]
    assert rep["beyond_lens_model"] == pytest.approx(1 / 17, abs=1e-4) and rep["outside_image"] == 0.0


def test_persons_too_close_are_both_dropped(pre, lab_intrinsics):
    p = pre()
    intr = lab_intrinsics["cam_4"]  # 640x480: limit 0.03 * 800 = 24 px between boxes
    a = _pixels(intr, _body([-0.3, 0.0, 5.0]))
    b = _pixels(intr, _body([0.1, 0.0, 5.0]))  # overlapping a
    far = _pixels(intr, _body([2.2, 0.0, 5.0]))
    # boxes from the keypoints (the sensor sent none)
    dets = p.view(_view("cam_4", [a, b, far], intr.resolution))
    assert len(dets) == 1 and dets[0].index == 2
    assert p.rejected["too_close"] == 2
    # boxes sent by the sensor are used: the same persons with boxes far apart are kept
    boxes = [[0, 0, 10, 10], [200, 200, 210, 210], [500, 400, 510, 410]]
    assert len(p.view(_view("cam_4", [a, b, far], intr.resolution, boxes=boxes))) == 3
    assert p.rejected["too_close"] == 2


def test_a_person_detected_twice_keeps_its_better_detection(pre, lab_intrinsics):
    # a top-down detector whose non-maximum suppression let two boxes on one person through
    p = pre()
    intr = lab_intrinsics["cam_4"]
    rng = np.random.default_rng(4)
    a = _pixels(intr, _body([-0.3, 0.0, 5.0]))
    again = a + rng.normal(0.0, 2.0, a.shape)  # the same joints from another crop
    conf = np.full(17, 0.9)
    conf_again = np.where(np.arange(17) % 5 == 0, 0.0, 0.8)  # fewer joints, lower
    far = _pixels(intr, _body([2.2, 0.0, 5.0]))
    kp = np.stack([np.c_[a, conf], np.c_[again, conf_again], np.c_[far, conf]])
    v = replace(_view("cam_4", [a, again, far], intr.resolution), kp=kp)
    dets = p.view(v)
    assert [d.index for d in dets] == [0, 2]
    assert p.rejected["duplicate"] == 1 and p.rejected["too_close"] == 0
    # the better one is kept whichever comes first; three copies keep one
    assert [d.index for d in p.view(replace(v, kp=kp[[1, 0, 2]]))] == [1, 2]
    third = np.c_[a + rng.normal(0.0, 2.0, a.shape), np.full(17, 0.7)]
    v4 = replace(_view("cam_4", [a, again, far, a], intr.resolution), kp=np.stack([*kp, third]))
    assert [d.index for d in p.view(v4)] == [0, 2]
    assert p.rejected["duplicate"] == 4
    # copies do not make a crowd
    few = pre(PreprocessConfig(max_persons=3))
    three = [_pixels(intr, _body([x, 0.0, 6.0])) for x in (-2.0, 0.0, 2.0)]
    twice = three + [uv + rng.normal(0.0, 1.0, uv.shape) for uv in three]
    assert [d.index for d in few.view(_view("cam_4", twice, intr.resolution))] == [0, 1, 2]
    assert few.rejected["duplicate"] == 3 and few.rejected["crowded_view"] == 0
    # off: the two overlap, and both go as too close (as before)
    off = pre(PreprocessConfig(duplicate_distance=0.0))
    assert [d.index for d in off.view(v)] == [2] and off.rejected["too_close"] == 2


def test_people_who_overlap_are_not_taken_for_duplicates(lab_intrinsics):
    intr = lab_intrinsics["cam_4"]
    a = _pixels(intr, _body([-0.3, 0.0, 5.0]))
    conf = np.full(17, 0.9)
    # side by side, a shoulder apart; one behind the other, smaller
    beside = _pixels(intr, _body([0.1, 0.0, 5.0]))
    behind = _pixels(intr, _body([-0.2, 0.0, 6.5], height=1.6))
    for b in (beside, behind):
        assert not duplicates(np.stack([np.c_[a, conf], np.c_[b, conf]]), 0.1).any()
    # a skeleton half on the person in front, half on the one it belongs to: no copy
    mixed = np.where(np.arange(17)[:, None] < 9, a, behind)
    assert not duplicates(np.stack([np.c_[a, conf], np.c_[mixed, conf]]), 0.1).any()
    # a copy is one, but not with fewer than 3 joints in common
    few = np.where(np.arange(17) < 2, 0.9, 0.0)
    assert duplicates(np.stack([np.c_[a, conf], np.c_[a + 1.0, conf]]), 0.1).tolist() == [False, True]
    assert not duplicates(np.stack([np.c_[a, conf], np.c_[a + 1.0, few]]), 0.1).any()


def test_crowded_views_are_dropped(pre, lab_intrinsics):
    intr = lab_intrinsics["cam_4"]
    p = pre(PreprocessConfig(max_persons=3, min_box_distance=0.0))
    persons = [_pixels(intr, _body([x, 0.0, 6.0])) for x in (-2.0, -1.0, 0.0, 1.0)]
    assert p.view(_view("cam_4", persons, intr.resolution)) == []
    assert p.rejected["crowded_view"] == 4
    assert len(p.view(_view("cam_4", persons[:3], intr.resolution))) == 3


def test_detections_below_the_threshold_do_not_crowd_a_view_but_still_hide_a_neighbour(pre, lab_intrinsics):
    # a real detector's low-score boxes: a dozen of them, away from the three real persons
    intr = lab_intrinsics["cam_4"]
    p = pre(PreprocessConfig(max_persons=3))
    real = [_pixels(intr, _body([x, 0.0, 6.0])) for x in (-2.0, 0.0, 2.0)]
    boxes = [[*uv.min(0), *uv.max(0)] for uv in real] + [[40.0 * k, 0.0, 40.0 * k + 10, 10.0] for k in range(12)]
    phantoms = [np.full((17, 2), 5.0) + [40.0 * k, 0.0] for k in range(12)]
    kp = np.stack([np.c_[uv, np.full(17, c)] for uv, c in zip(real + phantoms, [0.9] * 3 + [0.2] * 12)])
    v = replace(_view("cam_4", real + phantoms, intr.resolution, boxes=boxes), kp=kp)
    assert [d.index for d in p.view(v)] == [0, 1, 2]
    assert p.rejected["crowded_view"] == 0 and p.rejected["no_torso"] == 12
    # the same at the threshold are persons: the view is crowded
    crowd = kp.copy()
    crowd[3:, :, 2] = 0.9
    assert p.view(replace(v, kp=crowd)) == []
    assert p.rejected["crowded_view"] == 15
    # a low-score detection on top of a real person is most likely someone half hidden
    # behind it, whose keypoints mix with its: the person in front is dropped as too close
    behind = replace(v, boxes=np.array(boxes[:3] + [boxes[1]] + boxes[4:]))
    assert [d.index for d in p.view(behind)] == [0, 2] and p.rejected["too_close"] == 1


def test_sigma_from_the_sensor_covariance_or_the_confidence(pre, lab_intrinsics):
    p = pre()
    intr = lab_intrinsics["cam_4"]
    uv = _pixels(intr, _body([0.0, 0.0, 4.0]))
    cov = np.tile([9.0, 1.0, 16.0], (1, 17, 1))  # var x 9, y 16 px²
    [d] = p.view(_view("cam_4", [uv], intr.resolution, cov=cov))
    assert np.allclose(d.sigma, np.sqrt(12.5))
    conf = np.linspace(0.6, 1.0, 17)
    [d] = p.view(_view("cam_4", [uv], intr.resolution, conf=conf))
    assert np.allclose(d.sigma, PreprocessConfig().pixel_sigma * JOINT_NOISE / conf)
    # a nearest-message view 40 ms off, joints moving 100 px/s: 4 px more (in quadrature)
    speed = np.full((1, 17), 100.0)
    [d] = p.view(_view("cam_4", [uv], intr.resolution, cov=cov, offset=0.04, speed=speed))
    assert np.allclose(d.sigma, np.sqrt(12.5 + 16.0))
    # a zero (placeholder) covariance is no exact measurement: floored
    [d] = p.view(_view("cam_4", [uv], intr.resolution, cov=np.zeros((1, 17, 3))))
    assert np.allclose(d.sigma, PreprocessConfig().min_pixel_sigma)


def test_frameset_keeps_provenance_and_leaves_out_empty_views(pre, lab_intrinsics):
    p = pre()
    i0, i4 = lab_intrinsics["cam_0"], lab_intrinsics["cam_4"]
    v0 = _view("cam_0", [_pixels(i0, _body([0.5, 0.0, 4.0]))], i0.resolution, seq=11)
    v4 = _view("cam_4", [], i4.resolution)
    out = p(Frameset(100.0, (v0, v4)))
    assert len(out) == 1 and len(out[0]) == 1
    d = out[0][0]
    assert (d.cam, d.seq, d.index) == (0, 11, 0)
