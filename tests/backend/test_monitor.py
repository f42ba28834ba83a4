"""The monitor: a watched camera that is moved (3 cm, or 2°) is flagged within 30 s of data
and calibrated again from the data since the move; a camera network left alone, with
noisy keypoints, wrong associations and a slightly wrong calibration, is not flagged."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from backend.associate import Hypothesis
from backend.config import MonitorConfig
from backend.geometry import pose_local, pose_retract, project_normalised as _project, rotation_angle_deg, so3_exp
from backend.monitor import Alarm, Correspondences, Monitor, correspondences, resect

F = 425.0  # px
SWAP = 0.05  # share of frames with a view given to the wrong person
RATE = 5  # frames per second (the pipeline's 10, halved for the test's time)
CFG = MonitorConfig(enabled=True)


def _look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """world_R_cam of a camera at centre looking at target (x right, y down, z forward)."""
    z = target - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


class Scene:
    """8 cameras around a 4 m room, 2 persons walking in it, keypoints with 2 px noise,
    a little heavier-tailed, and now and then a view given to the wrong person."""

    def __init__(self, seed: int, occluded: float = 0.2):
        self.rng = np.random.default_rng(seed)
        self.occluded = occluded  # chance a camera does not see a person in a frame
        self.dropped: dict[int, float] = {}  # camera: chance its view is left out of a hypothesis
        C = 8
        ang = np.linspace(0, 2 * np.pi, C, endpoint=False)
        self.t = np.stack([4 * np.cos(ang), 4 * np.sin(ang), np.full(C, 2.5)], axis=1)
        self.R = np.array([_look_at(c, np.array([0.0, 0.0, 1.0])) for c in self.t])
        self.body = self.rng.normal(0, 0.25, size=(2, 17, 3)) + np.array([0, 0, 0.9])
        self.pos = self.rng.uniform(-1.5, 1.5, size=(2, 2))
        self.vel = np.zeros((2, 2))
        # the calibration the monitor works with: a little off the truth (0.5 cm, 0.05°)
        self.R_est, self.t_est = self.R.copy(), self.t.copy()
        for c in range(C):
            self.R_est[c], self.t_est[c] = pose_retract(self.R[c], self.t[c], np.r_[
                self.rng.normal(0, np.radians(0.05), 3), self.rng.normal(0, 0.005, 3)])

    def bump(self, c: int, translation: float, rotation_deg: float) -> None:
        d = self.rng.normal(size=3)
        w = self.rng.normal(size=3)
        self.t[c] = self.t[c] + translation * d / np.linalg.norm(d)
        self.R[c] = so3_exp(np.radians(rotation_deg) * w / np.linalg.norm(w)) @ self.R[c]

    def frame(self, time: float) -> list[Hypothesis]:
        """The persons 1/RATE s later, as hypotheses."""
        rng = self.rng
        self.vel = 0.8 * self.vel + rng.normal(0, 0.1, size=(2, 2))
        self.pos = np.clip(self.pos + self.vel / RATE, -1.8, 1.8)
        hyps = []
        seen = []
        for k in range(2):
            X = self.body[k] + np.r_[self.pos[k], 0.0]
            cams, xy = [], []
            for c in range(len(self.t)):
                if rng.random() < self.occluded or (c in self.dropped and rng.random() < self.dropped[c]):
                    continue
                uv, _ = _project(self.R[c], self.t[c], X)
                noise = rng.standard_t(5, size=(17, 2)) * 2.0 / F
                cams.append(c)
                xy.append(uv + noise)
            seen.append((cams, xy, X))
        if rng.random() < SWAP and seen[0][0] and seen[1][0]:  # a view given to the other person
            seen[0][1][0], seen[1][1][0] = seen[1][1][0], seen[0][1][0]
        for cams, xy, X in seen:
            if len(cams) >= 2:
                hyps.append(Hypothesis(time, np.array(cams), np.array(xy), np.full((len(cams), 17), 2.0 / F),
                                       X.mean(0)))
        return hyps


def _run(seed: int, bump: tuple[float, float] | None, duration: float, cam: int = 2, bump_time: float = 120.0,
         occluded: float = 0.2, dropped: float = 0.0, short: bool = False, sparse: float = 0.0):
    """The monitor fed the scene at RATE Hz and evaluated every 0.5 s as the pipeline does
    after its cycles; recalibrated poses are applied. ``dropped``: the share of the moved
    camera's views left out of the hypotheses after the move; ``short``: the camera's own
    bins before the move dropped (as a camera has whose bins mostly fall short of
    ``min_points``); ``sparse``: the share of its views left out from the start (a camera
    that sees little). Returns (scene, monitor, alarms, the camera's pose error at the end)."""
    s = Scene(seed, occluded)
    if sparse:
        s.dropped[cam] = sparse
    m = Monitor(CFG, np.full(8, F))
    watched = np.ones(8, bool)
    alarms = []
    t_start = s.t_est.copy()
    for i in range(int(duration * RATE)):
        time = i / RATE
        if bump is not None and i == int(bump_time * RATE):
            s.bump(cam, *bump)
            if dropped:
                s.dropped[cam] = dropped
            if short:
                m.cams[cam].bins.clear()
        m.add(s.frame(time))
        if i % (RATE // 2) == RATE // 2 - 1:
            found, poses = m.evaluate(time, watched & ~m.recalibrating(), s.R_est, s.t_est)
            alarms += found
            for a in found:
                watched[a.cam] = False
            for r in poses:
                s.R_est[r.cam], s.t_est[r.cam] = r.R, r.t
            # once calibrated again, watched again
            watched |= ~m.recalibrating()
    err = (float(np.linalg.norm(s.t_est[cam] - s.t[cam])), rotation_angle_deg(s.R_est[cam], s.R[cam]))
    others = np.arange(8) != cam
    s.others_moved = float(np.max(np.linalg.norm(s.t_est[others] - t_start[others], axis=1)))
    return s, m, alarms, err


@pytest.mark.parametrize("bump", [(0.03, 0.0), (0.0, 2.0)], ids=["3cm", "2deg"])
def test_a_bumped_camera_is_flagged_within_30s_and_calibrated_again(bump):
    s, m, alarms, err = _run(1, bump, 200.0)  # bumped at 120 s
    assert alarms, "not flagged"
    a = alarms[0]
    assert a.cam == 2 and 120.0 < a.time <= 150.0, alarms
    assert [x.cam for x in alarms] == [2]  # no other camera
    assert 110.0 <= a.since <= a.time
    # the cameras it was a source of points for started their reference over, without it
    assert all(b[0] >= a.time for c in range(8) if c != 2 for b in m.cams[c].bins)
    # each bin says where in the image its points were, for the test's bias by where
    assert all(np.all(np.abs(b[4]) < 1.0) for k in m.cams for b in k.bins) and any(k.bins for k in m.cams)
    assert err[0] < 0.03 and err[1] < 0.3, err  # 80 s after the bump
    assert s.others_moved < 0.005  # the others are held


def test_the_moved_camera_is_blamed_not_one_whose_points_it_biased():
    """Half the views missing, so a camera's points come from few others, and the moved
    camera's views mostly no longer joining hypotheses (as when the association gates them
    by its old pose): another camera's points lean on the moved one, and its test failed
    first (camera 1 at 155 s before the blame rule). Tested again without the moved
    camera's rays its step is gone: only the moved camera is flagged."""
    _, _, alarms, _ = _run(1, (0.03, 0.0), 200.0, occluded=0.5, dropped=0.6)
    assert [a.cam for a in alarms] == [2], alarms


def test_a_camera_bumped_with_too_short_a_reference_is_blamed_on_the_others_evidence():
    """Camera 2 turned 2° with too few bins of its own before (a camera that sees little):
    its own test cannot show the step, while the cameras its rays reach step, and step no
    more without them. It is flagged on their evidence (before, nobody was, or camera 4),
    with its step's size from its bins since, and no other camera is."""
    _, m, alarms, err = _run(1, (0.0, 2.0), 240.0, short=True)
    assert [a.cam for a in alarms] == [2], alarms
    assert alarms[0].time < 150.0 and 1.0 < alarms[0].rotation < 3.0, alarms
    assert err[1] < 0.3, err  # calibrated again


def test_a_camera_that_sees_little_gets_longer_bins_and_is_flagged():
    """Camera 2 in a tenth of the hypotheses: ~70 joints per 5 s, fewer than
    ``min_points``. Its bins stay open over grid steps until they have enough (before,
    a 5 s bin counted only now and then, and the camera turned 2° was flagged 80 s later
    on this seed, never on seeds 2 and 3). Turned at 120 s, it is flagged within 50 s
    (21 s) and calibrated again; nobody else is."""
    _, m, alarms, err = _run(1, (0.0, 2.0), 240.0, sparse=0.9)
    assert [a.cam for a in alarms] == [2], alarms
    assert alarms[0].time < 170.0, alarms
    assert err[1] < 0.3, err
    spans = [b[1] - b[0] for b in m.cams[2].bins]
    assert spans and max(spans) > CFG.bin_seconds + 1.0, spans  # bins of several grid steps


@pytest.mark.parametrize("bump", [(0.03, 0.0), (0.0, 2.0)], ids=["3cm", "2deg"])
def test_a_camera_bumped_early_in_its_watch_is_flagged_and_calibrated_again(bump):
    """Bumped 25 s after the watch began (a live session's watch begins while it is still
    calibrating): 5 bins before the move, fewer than ``min_reference_bins``. Before, no
    split had a reference long enough, ever: the camera was never flagged and stayed held
    where it was. Now it is flagged once it has ``min_reference_bins`` bins, on its own
    bins' scatter about their means on both sides, and calibrated again."""
    _, m, alarms, err = _run(1, bump, 160.0, bump_time=25.0)
    assert [a.cam for a in alarms] == [2], alarms
    assert 25.0 < alarms[0].time <= 25.0 + 60.0 and 15.0 <= alarms[0].since <= 30.0, alarms
    assert err[0] < 0.03 and err[1] < 0.3, err
    assert not m.cams[2].first_watch  # its next watch is tested on full references only


def test_short_references_only_in_a_cameras_first_watch():
    """A step after 4 of 14 bins fails a camera's test in its first watch, not in a watch
    begun after an alarm (whose first minute differs from the next by what the alarm did)."""
    rng = np.random.default_rng(5)
    m = Monitor(CFG, np.full(8, F))
    k = m.cams[1]
    k.bins = _bins(rng, np.r_[0, 0, 0, 0.05, 0, 0], since=20.0, n=14)
    a = m._test(1, k, 70.0)
    assert a is not None and a.since == 20.0 and abs(a.translation - 0.05) < 0.01, a
    k.first_watch = False
    assert m._test(1, k, 70.0) is None


def test_a_short_reference_finds_a_step_but_no_step_in_quiet_bins():
    """``change_test`` on 14 bins whose step (5 cm) comes after 4: found at that split,
    and not with short references turned off; in 100 quiet sequences of 14 bins (the
    bins' errors larger than their informations say, as real bins' are) nothing is."""
    from backend.monitor import change_test

    rng = np.random.default_rng(11)
    sd = np.r_[[np.radians(0.05)] * 3, [0.004] * 3]
    W = np.repeat(np.diag(1 / sd ** 2)[None], 14, axis=0)
    start = 5.0 * np.arange(14)
    now = start[-1] + 5.0
    moved = rng.normal(size=(14, 6)) * sd * 2.0
    moved[4:, 3] += 0.05
    found = change_test(moved, W, start, now, CFG, np.zeros((6, 6)))
    assert found is not None and found[3] == start[4] and abs(found[1] - 0.05) < 0.02, found
    off = CFG.model_copy(update={"short_reference_bins": CFG.min_reference_bins})
    assert change_test(moved, W, start, now, off, np.zeros((6, 6))) is None
    quiet = [change_test(rng.standard_t(5, size=(14, 6)) * sd * 2.0, W, start, now, CFG, np.zeros((6, 6)))
             for _ in range(100)]
    assert quiet == [None] * 100


def test_a_camera_with_long_bins_keeps_a_step_under_test_for_as_many_bins():
    """A camera that sees little: a bin every 15 s. A 5 cm step 8 bins (120 s) ago is
    still under test (the window is 60 s or 12 bins, whichever reaches further back);
    with a window of 60 s only, its split had left it."""
    from backend.monitor import _step_at, change_test

    rng = np.random.default_rng(3)
    sd = np.r_[[np.radians(0.05)] * 3, [0.004] * 3]
    n = 20
    W = np.repeat(np.diag(1 / sd ** 2)[None], n, axis=0)
    start = 15.0 * np.arange(n)
    now = start[-1] + 15.0
    z = rng.normal(size=(n, 6)) * sd
    z[12:, 4] += 0.05
    found = change_test(z, W, start, now, CFG, np.zeros((6, 6)))
    assert found is not None and found[3] == start[12] and abs(found[1] - 0.05) < 0.01, found
    timed = CFG.model_copy(update={"bin_seconds": 15.0})  # 60 s are 4 of its bins
    found = change_test(z, W, start, now, timed, np.zeros((6, 6)))
    assert found is None or found[3] != start[12], found
    # the step at one given split (the blame's) stays at that split
    bins = [(s0, s0 + 15.0, z[i], W[i]) for i, s0 in enumerate(start)]
    assert _step_at(bins, start[16], now, CFG, np.zeros((6, 6)))[3] == start[16]


def _five_second_bins(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """n 5 s bins of a camera whose resections have 0.05° / 4 mm noise: (their std (6,),
    informations (n, 6, 6), starts (n,), the data time after the last)."""
    sd = np.r_[[np.radians(0.05)] * 3, [0.004] * 3]
    start = 5.0 * np.arange(n)
    return sd, np.repeat(np.diag(1 / sd ** 2)[None], n, axis=0), start, start[-1] + 5.0


def test_people_moving_across_a_biased_view_are_no_step_but_a_move_wherever_they_are_is():
    """A lens a little off biases a camera's data-only pose by where its people are in
    the image (here 0.8° and 6 cm per unit of the normalised image across). People who
    walk from its left to its right half make a step of 0.4° / 3 cm in its bins: not
    flagged when the test knows where each bin's points were (``where``), flagged without.
    A move of 5 cm with the same bias, while the people walk all over the view, is found
    at its split."""
    from backend.monitor import change_test

    rng = np.random.default_rng(5)
    n, split = 24, 16
    sd, W, start, now = _five_second_bins(n)
    bias = np.r_[0.0, np.radians(0.8), 0.0, 0.06, 0.0, 0.0]  # per unit of the image's x

    def bins(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        where = np.stack([x, rng.uniform(-0.2, 0.2, n)], axis=1)
        return rng.normal(size=(n, 6)) * sd + where[:, :1] * bias, where

    crossing, where = bins(np.r_[rng.uniform(-0.5, 0.0, split), rng.uniform(0.0, 0.5, n - split)])
    assert change_test(crossing, W, start, now, CFG, np.zeros((6, 6)), where=where) is None
    assert change_test(crossing, W, start, now, CFG, np.zeros((6, 6))) is not None
    off = CFG.model_copy(update={"where_covariates": False})
    assert change_test(crossing, W, start, now, off, np.zeros((6, 6)), where=where) is not None

    moved, where = bins(rng.uniform(-0.5, 0.5, n))
    moved[split:, 3] += 0.05
    found = change_test(moved, W, start, now, CFG, np.zeros((6, 6)), where=where)
    assert found is not None and found[3] == start[split] and abs(found[1] - 0.05) < 0.02, found


def test_a_lens_off_its_calibration_is_no_step_when_the_people_go_deeper_but_a_move_is():
    """A focal length 1.5 % short of the calibration file's moves a camera's data-only
    pose along its axis by 1.5 % of its people's depth. People who walk from 3-5 m to
    8-10 m away, in the middle of the view (where they are in the image does not change),
    make a step of about 7 cm along the axis in its bins: not flagged when the test knows
    each bin's sensitivity to the lens (``lens``), flagged without it. A move of 5 cm
    sideways while they do the same is found at its split."""
    from backend.monitor import change_test

    rng = np.random.default_rng(5)
    n, split = 24, 16
    sd, W, start, now = _five_second_bins(n)
    depth = np.r_[rng.uniform(3.0, 5.0, split), rng.uniform(8.0, 10.0, n - split)]
    lens = np.zeros((n, 6, 4))  # per 1 % of the focal lengths (x, y) and of the principal point
    lens[:, 5, 0] = lens[:, 5, 1] = 0.005 * depth  # along the axis, half from each focal length
    lens[:, 1, 2] = lens[:, 0, 3] = 0.01  # a shifted principal point turns the camera
    error = np.array([-1.5, -1.5, 0.5, 0.0])  # %
    where = np.stack([rng.uniform(-0.1, 0.1, n), rng.uniform(-0.1, 0.1, n)], axis=1)
    deeper = rng.normal(size=(n, 6)) * sd + lens @ error
    assert change_test(deeper, W, start, now, CFG, np.zeros((6, 6)), where=where, lens=lens) is None
    assert change_test(deeper, W, start, now, CFG, np.zeros((6, 6)), where=where) is not None
    off = CFG.model_copy(update={"lens_covariates": False})
    assert change_test(deeper, W, start, now, off, np.zeros((6, 6)), where=where, lens=lens) is not None

    moved = deeper.copy()
    moved[split:, 3] += 0.05
    found = change_test(moved, W, start, now, CFG, np.zeros((6, 6)), where=where, lens=lens)
    # its size is the bins' step: the move and the people's depth together
    assert found is not None and found[3] == start[split] and found[1] > 0.05, found


def test_a_resection_says_how_a_lens_error_moves_it():
    """``Resection.lens``: the pose a resection finds from keypoints whose focal length is
    1 % longer in x than the calibration's moves, to first order, by its first column."""
    rng = np.random.default_rng(2)
    R, t = _look_at(np.array([4.0, 0.0, 2.5]), np.array([0.0, 0.0, 1.0])), np.array([4.0, 0.0, 2.5])
    X = np.c_[rng.uniform(-2.5, 2.5, (300, 2)), rng.uniform(0.1, 1.8, 300)]
    xy, _ = _project(R, t, X)

    def resected(scale: float):
        data = [Correspondences(0.0, X, xy * [1 + scale, 1.0], np.full(len(X), 1 / F), np.zeros(len(X), int))]
        return resect(R, t, data, F, outlier_px=15.0)

    exact, longer = resected(0.0), resected(0.01)
    moved = pose_local(exact.R, exact.t, longer.R, longer.t)
    assert exact.lens.shape == (6, 4) and np.linalg.norm(moved) > 1e-3
    assert np.linalg.norm(moved - exact.lens[:, 0]) < 0.05 * np.linalg.norm(moved), (moved, exact.lens[:, 0])


def test_two_odd_bins_are_no_step_when_the_cameras_bins_are_often_odd():
    """Lenses a little off and keypoints on the outline make a camera's bins odd now and
    then (lab seed 304's cam_19: 3 of the 33 bins before its window beyond the 99th
    percentile, and two of the nine after a split, in different directions, which made a
    false alarm on their own). Two strong odd bins among weak ones after a split: a step
    when the camera's reference has no odd bin (two in nine are then unlikely), none when
    its reference has three; with that reference a move is found at its split by the
    weak bins alone (8 cm; 4 cm is not yet: the two strong bins that show it are what
    odd bins look like, and agreeing with the rest does not keep them then)."""
    from backend.monitor import _odd_bins, change_test

    assert _odd_bins(9, 3.5 / 34, 0.05) == 3 and _odd_bins(9, 0.5 / 34, 0.05) == 1
    rng = np.random.default_rng(11)
    sd = np.r_[[np.radians(0.1)] * 3, [0.01] * 3]
    n, split = 45, 36
    scale = np.ones(n)
    scale[split + 1:n - 1] = 3.0  # weak bins after the split ...
    scale[[split, n - 1]] = 0.5  # ... but its first and last
    W = np.diag(1 / sd ** 2)[None] / scale[:, None, None] ** 2
    start = 5.0 * np.arange(n)
    now = start[-1] + 5.0
    z = rng.normal(size=(n, 6)) * sd * scale[:, None]
    z[split, [3, 5]] += [3 * sd[3], -3 * sd[5]]
    z[n - 1, [3, 4]] += 3 * sd[3:5]
    assert change_test(z, W, start, now, CFG, np.zeros((6, 6))) is not None
    often = z.copy()
    for i, k in zip((5, 17, 29), (3, 4, 5)):
        often[i, k] += 6 * sd[k]
    assert change_test(often, W, start, now, CFG, np.zeros((6, 6))) is None
    moved = often.copy()
    moved[split:, 3] += 0.04
    assert change_test(moved, W, start, now, CFG, np.zeros((6, 6))) is None
    moved[split:, 3] += 0.04  # 8 cm
    found = change_test(moved, W, start, now, CFG, np.zeros((6, 6)))
    assert found is not None and found[3] == start[split] and found[1] > 0.06, found


def test_odd_bins_that_agree_with_each_other_are_no_step_when_the_cameras_bins_are_often_odd():
    """Lab seed 263, no camera moved: cam_10's bins at the false alarm of its watch (710.4 s
    of data, the bench's quiet protocol; tests/backend/data, the monitor's own bins). Six
    bins after the split at 675.4 s, three of them odd against the reference (χ² 31-45),
    each agreeing with the other five (χ² 11-17 < the 99th percentile); the reference has
    3 odd bins of 33. Kept as agreeing they made a step of 2.7 cm at χ² 42.3; left out, as
    odd bins of such a camera, they make none. The same bins with 2 cm added after the
    split make a step, at that split."""
    from backend.monitor import change_test

    x = np.load(Path(__file__).parent / "data" / "monitor_lab_seed263_cam10.npz")
    floor = np.diag([np.radians(CFG.model_std_rotation) ** 2] * 3 + [CFG.model_std_translation ** 2] * 3)
    z, args = x["z"].copy(), (x["info"], x["start"], float(x["now"]), CFG, floor)
    assert change_test(z, *args, where=x["where"], lens=x["lens"]) is None
    assert change_test(z, *args, leave_one_out=False) is not None  # the six bins do step
    z[x["start"] >= 675.0, 3] += 0.02
    found = change_test(z, *args, where=x["where"], lens=x["lens"])
    assert found is not None and abs(found[3] - 675.36) < 0.1 and found[1] > 0.03, found


def _bins(rng: np.random.Generator, step: np.ndarray, since: float, n: int = 24) -> list:
    """n 5 s bins of a camera's resections (start, end, z, info): noise of 0.03° / 1 mm,
    ``step`` (6,) added from ``since`` on."""
    sd = np.r_[[np.radians(0.03)] * 3, [0.001] * 3]
    return [(5.0 * i, 5.0 * (i + 1), rng.normal(0, sd) + (step if 5.0 * i >= since else 0.0), np.diag(1 / sd**2))
            for i in range(n)]


SINCE = 90.0  # data time of the hand-made steps


def _watched_with_steps(steps: dict[int, np.ndarray], since: float) -> tuple[Monitor, np.ndarray, np.ndarray]:
    """A monitor whose cameras ``steps`` (camera: step (6,) from ``since`` on) are watched,
    with 24 bins each (``_bins``), trusting everyone else, and hypotheses seen by all of
    them since then, so none can be tested without another. Returns (monitor, R, t)."""
    rng = np.random.default_rng(0)
    m = Monitor(CFG, np.full(8, F))
    scene = Scene(0)
    R, t = scene.R_est, scene.t_est
    for c, step in steps.items():
        m.cams[c].bins = _bins(rng, step, since)
        m.cams[c].anchor, m.cams[c].trust = (R[c], t[c]), np.arange(8) != c
    cams = np.array(sorted(steps))
    xy = rng.normal(0, 0.1, (len(cams), 17, 2))
    m.recent.extend(Hypothesis(since + 1 + k, cams, xy, np.full((len(cams), 17), 0.005), np.zeros(3))
                    for k in range(20))
    return m, R, t


@pytest.mark.parametrize("moved", [0.06, 0.01, 0.0])
def test_a_step_nobody_explains_is_flagged_where_it_is_largest(moved):
    """Camera 1 fails (a 2 cm step), its points came from camera 2 alone, so it cannot be
    tested without it. Camera 2's own bins show a 6 cm step at the same time: camera 2 is
    the moved one (a move induces a smaller step in another). A smaller step of camera 2's
    (1 cm), or none, leaves the alarm camera 1's."""
    m, R, t = _watched_with_steps({1: np.r_[0, 0, 0, 0.02, 0, 0], 2: np.r_[0, 0, 0, 0, moved, 0]}, SINCE)
    now = SINCE + 30.0
    a = m._test(1, m.cams[1], now)
    assert a is not None and a.cam == 1 and a.chi2 > CFG.chi2
    blamed = m._blame(a, now, np.ones(8, bool), R, t)
    assert blamed is not None and blamed.cam == (2 if moved > 0.02 else 1), blamed
    if moved > 0.02:
        assert blamed.chi2 > a.chi2 and abs(blamed.translation - moved) < 0.005


@pytest.mark.parametrize("judged", [False, True])
def test_nobody_is_blamed_while_a_source_is_too_new_to_judge(judged):
    """Camera 1 fails (a 2 cm step); its points came from cameras 2 and 3, so it cannot be
    tested without either. Camera 2's own bins show a 6 cm step, but camera 3 has one bin
    since the change, too few to show its own: it may be the moved one, and camera 2's
    step its doing (the west room mid-session: the camera flagged so was calibrated again
    against the moved one, and the others moved 9 cm). Nobody is flagged yet; once camera
    3 has bins enough and shows no step, camera 2 is."""
    m, R, t = _watched_with_steps({1: np.r_[0, 0, 0, 0.02, 0, 0], 2: np.r_[0, 0, 0, 0, 0.06, 0], 3: np.zeros(6)},
                                  SINCE)
    if not judged:
        m.cams[3].bins = [b for b in m.cams[3].bins if b[0] < SINCE + 5.0]  # one bin since
    now = SINCE + 30.0
    a = m._test(1, m.cams[1], now)
    assert a is not None and a.cam == 1 and a.chi2 > CFG.chi2
    blamed = m._blame(a, now, np.ones(8, bool), R, t)
    if judged:
        assert blamed is not None and blamed.cam == 2, blamed
    else:
        assert blamed is None, blamed


def test_a_quiet_network_raises_no_alarm():
    _, m, alarms, _ = _run(2, None, 300.0)
    assert alarms == []
    assert all(len(k.bins) >= CFG.min_reference_bins for k in m.cams)  # it was tested


def test_unwatched_or_disabled_cameras_are_never_flagged():
    for cfg, watch in ((CFG, [c != 2 for c in range(8)]), (MonitorConfig(enabled=False), [True] * 8)):
        s = Scene(3)
        m = Monitor(cfg, np.full(8, F))
        watched = np.array(watch)
        for i in range(150 * RATE):
            if i == 60 * RATE:
                s.bump(2, 0.1, 5.0)
            m.add(s.frame(i / RATE))
            if i % RATE == 0:
                assert m.evaluate(i / RATE, watched, s.R_est, s.t_est) == ([], [])


def test_resection_recovers_a_pose_and_drops_a_wrong_view():
    rng = np.random.default_rng(4)
    R = so3_exp(rng.normal(size=3))
    t = rng.normal(size=3)
    X = t + np.c_[rng.normal(size=(340, 2)), 3 + 2 * rng.random(340)] @ R.T
    R1, t1 = pose_retract(R, t, np.r_[0.03, -0.02, 0.01, 0.05, 0.02, -0.03])
    uv, J = _project(R1, t1, X)
    # the Jacobian is the one of pose_retract's perturbation
    for i in range(6):
        Rp, tp = pose_retract(R1, t1, 1e-6 * np.eye(6)[i])
        np.testing.assert_allclose((_project(Rp, tp, X)[0] - uv) / 1e-6, J[:, :, i], atol=1e-4)
    xy = uv + rng.normal(size=uv.shape) * 1.0 / F
    view = np.arange(340) // 17
    xy[view == 3] += 40 / F  # a wrong association: 40 px off
    r = resect(R, t, [Correspondences(0.0, X, xy, np.full(340, 1.0 / F), view)], F, outlier_px=15.0)
    assert r is not None and r.views == 19 and r.points == 340 - 17
    d = pose_local(R1, t1, r.R, r.t)
    assert np.linalg.norm(d[3:]) < 0.01 and np.degrees(np.linalg.norm(d[:3])) < 0.1
    assert r.rms_px < 2.0
    assert resect(R, t, [], F, outlier_px=15.0) is None


def test_correspondences_use_only_trusted_others():
    s = Scene(5)
    hyps = s.frame(0.0)
    trusted = np.ones(8, bool)
    trusted[[0, 1]] = False
    out = correspondences(hyps, s.R, s.t, trusted, np.full(8, F), 2.0, 15.0)
    assert out and set(out) <= set(np.concatenate([h.cams for h in hyps]).tolist())
    for c, items in out.items():
        for it in items:
            # points triangulated from the (noisy) others land near the person
            assert np.all(np.linalg.norm(it.X - hyps[0].com, axis=1) < 3.0) or \
                np.all(np.linalg.norm(it.X - hyps[-1].com, axis=1) < 3.0)
    assert correspondences(hyps, s.R, s.t, np.zeros(8, bool), np.full(8, F), 2.0, 15.0) == {}


def test_one_odd_bin_is_no_step_three_moved_bins_are():
    from backend.monitor import change_test

    rng = np.random.default_rng(6)
    sd = np.r_[[np.radians(0.1)] * 3, [0.01] * 3]
    W = np.repeat(np.diag(1 / sd ** 2)[None], 30, axis=0)
    z = rng.normal(size=(30, 6)) * sd
    start = 5.0 * np.arange(30)
    now = start[-1] + 5.0
    odd = z.copy()
    odd[-3] += 4 * sd  # one bin far off (10 sigmas), the two after it as before
    assert change_test(odd, W, start, now, CFG, np.zeros((6, 6))) is None
    moved = z.copy()
    moved[-3:, 3] += 0.05  # the camera moved by 5 cm three bins ago
    found = change_test(moved, W, start, now, CFG, np.zeros((6, 6)))
    assert found is not None and found[3] == start[-3] and abs(found[1] - 0.05) < 0.02


def test_a_strong_bin_after_a_step_counts_when_the_others_agree_with_it():
    """Three bins after a step, one with four times the information of a reference bin and
    two weaker than one: the step is significant without the strong bin only at
    χ² about 30, but the strong bin is where the other two put the camera, so it is no
    odd bin to leave out (the bar's seed 1 waited 50 s for a second strong bin). The same
    strong bin moved alone, the other two where the reference is, is still no step."""
    from backend.monitor import change_test

    rng = np.random.default_rng(7)
    sd = np.r_[[np.radians(0.1)] * 3, [0.01] * 3]
    W = np.repeat(np.diag(1 / sd ** 2)[None], 30, axis=0)
    W[-3:-1] /= 1.5 ** 2  # two weaker bins
    W[-1] *= 4.0  # and a strong one
    z = rng.normal(size=(30, 6)) * sd / np.sqrt(np.diagonal(W, axis1=1, axis2=2) * sd ** 2)
    start = 5.0 * np.arange(30)
    now = start[-1] + 5.0
    moved = z.copy()
    moved[-3:, 3] += 5 * sd[3]  # the camera moved by 5 cm three bins ago
    found = change_test(moved, W, start, now, CFG, np.zeros((6, 6)))
    assert found is not None and found[3] == start[-3] and abs(found[1] - 0.05) < 0.02
    odd = z.copy()
    odd[-1, 3] += 5 * sd[3]  # only the strong bin
    assert change_test(odd, W, start, now, CFG, np.zeros((6, 6))) is None


def test_a_step_is_found_in_bins_whose_rotation_and_translation_are_correlated():
    """A bin's resection pins a mix of rotation and translation tightly and the other mix
    loosely, along different directions in different bins (where the people were). The
    coordinate-wise median of three such bins after a move lies far from each of them in
    their own metric: the robust mean must not reject them all (lab seed 0, cam_8 turned
    2°, found 5 s late; a reference with none kept gave a NaN χ² that passed as an alarm)."""
    from backend.monitor import _mean, change_test

    rng = np.random.default_rng(3)
    tight, loose = 0.002, 0.02  # std along the pinned and the free mix (rad ~ m here)
    u = np.array([1.0, 1.0]) / np.sqrt(2)
    v = np.array([1.0, -1.0]) / np.sqrt(2)

    def info(free: np.ndarray) -> np.ndarray:
        W = np.diag(1 / np.r_[[np.radians(0.1)] * 3, [0.01] * 3] ** 2)
        pinned = np.array([-free[1], free[0]])
        S = tight ** 2 * np.outer(pinned, pinned) + loose ** 2 * np.outer(free, free)
        W[np.ix_([0, 4], [0, 4])] = np.linalg.inv(S)  # rotation about x with translation along y
        return W

    n = 20
    frees = [u if k % 2 else v for k in range(n)]
    W = np.array([info(f) for f in frees])
    z = np.array([rng.multivariate_normal(np.zeros(6), np.linalg.inv(w)) for w in W])
    z[:, [0, 4]] = [rng.normal(0, tight) * np.array([-f[1], f[0]]) + rng.normal(0, loose) * f for f in frees]
    step = np.array([0.0, 0.0, 0.0, 0.0, 0.05, 0.0])  # 5 cm along y
    after = [(u, 0.025), (v, 0.025), (u, -0.025)]  # along each bin's free mix, as it may be
    W[-3:] = [info(f) for f, _ in after]
    z[-3:] = step + np.array([np.r_[a * f[0], 0.0, 0.0, 0.0, a * f[1], 0.0] for f, a in after])
    m, _, _, kept = _mean(z[-3:], W[-3:], 1.0)
    assert kept == 3 and np.allclose(m, step, atol=1e-3)
    start = 5.0 * np.arange(n)
    found = change_test(z, W, start, start[-1] + 5.0, CFG, np.zeros((6, 6)))
    # (the bin before the move may join the step: its own free mix leans the same way)
    assert found is not None and np.isfinite(found[0]) and found[0] > CFG.chi2 and found[3] >= start[-4]
    assert found[1] > CFG.min_translation


def test_points_far_from_the_others_weigh_less():
    """A point the others place only to 10 cm, seen from 1 m, is no exact point."""
    rng = np.random.default_rng(7)
    R = np.eye(3)
    t = np.zeros(3)
    X = np.c_[rng.normal(size=(200, 2)), 3 + rng.random(200)]
    uv, _ = _project(R, t, X)
    sig = np.full(200, 1.0 / F)
    exact = resect(R, t, [Correspondences(0.0, X, uv, sig, np.arange(200) // 17)], F, outlier_px=15.0)
    loose = resect(R, t, [Correspondences(0.0, X, uv, sig, np.arange(200) // 17,
                                          np.repeat(0.01 * np.eye(3)[None], 200, axis=0))], F, outlier_px=15.0)
    assert exact is not None and loose is not None
    assert np.all(np.linalg.eigvalsh(exact.info - loose.info) > -1e-6)  # less information
    assert np.trace(np.linalg.inv(loose.info)) > 10 * np.trace(np.linalg.inv(exact.info))


@pytest.mark.parametrize("without_8, flagged", [(10.4, 8), (30.0, 9)])
def test_a_step_that_falls_to_a_quarter_without_a_camera_is_blamed_on_it(monkeypatch, without_8, flagged):
    """The blame's rule on the lab's case (seed 1, lenses 1 % off, keypoints on the outline,
    cam_8 turned 2°): cam_9's test fails first (χ² 108.6); without cam_8's rays its step
    falls to χ² 10.4, over a quarter of the threshold (lenses off leave a little step of
    their own in every camera), and without cam_3's it stays; cam_8's own bins step (χ²
    1242, 2.1°). No longer significant and a quarter of what it was: cam_8 is flagged,
    not cam_9 (before, cam_9 was, and calibrated again against the moved camera). A fall
    to χ² 30, still over a quarter of 108.6, leaves the alarm cam_9's."""
    import backend.monitor as monitor

    m = Monitor(CFG, np.full(10, F))
    m.cams[8].anchor = (np.eye(3), np.zeros(3))  # watched
    a = Alarm(250.0, 9, 108.6, 0.235, 0.65, 235.0)
    without = {8: (without_8, 0.081, 0.354, None), 3: (94.0, 0.188, 0.436, None)}
    monkeypatch.setattr(m, "_suspects", lambda alarm, watched: [8, 3])
    monkeypatch.setattr(m, "_bins_without", lambda alarm, j, R, t: j)  # stands for the bins without j
    monkeypatch.setattr(monitor, "_step_at", lambda bins, since, now, cfg, floor: without[bins])
    monkeypatch.setattr(m, "_unjudged", lambda j, alarm: False)
    monkeypatch.setattr(m, "_own_step", lambda j, alarm, now: {8: (1242.0, 0.033, 2.08, None),
                                                                   9: (108.6, 0.235, 0.65, None)}.get(j))
    got = m._blame(a, 250.0, np.ones(10, bool), np.zeros((10, 3, 3)), np.zeros((10, 3)))
    assert got is not None and got.cam == flagged, got
