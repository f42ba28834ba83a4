"""The engine's parameters: one typed, frozen config, the paper's defaults.

Loaded from TOML (sections = the stage names below) and overridden from the CLI
(``--set optimize.scope=80``) or a session's JSON ``config``. Unknown keys are errors.
"""

from __future__ import annotations

import math
import statistics
import tomllib
from collections.abc import Iterable
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, PositiveInt, ValidationError, field_validator


class _Section(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class SyncConfig(_Section):
    """Framesets from free-running sensors."""

    rate: float = Field(10.0, gt=0, le=200, description="framesets per second of data time")
    max_offset: float = Field(0.05, gt=0, description="s: a sensor whose nearest message is further from the frameset time sits out")
    max_span: float = Field(0.05, gt=0, description="s: reject a frameset whose used stamps span more (paper: 50 ms)")
    max_std: float = Field(0.025, gt=0, description="s: reject a frameset whose stamp std is larger (paper: 25 ms)")
    interpolate: bool = Field(True, description="interpolate each sensor's keypoints to the frameset time from its two bracketing messages")
    max_gap: float = Field(0.6, gt=0, description="s: longest interval between a sensor's two bracketing messages that is "
                           "interpolated across (a 2 Hz sensor; a longer one is a gap: a stall, the sensor sits out). Was "
                           "2 x max_offset (0.1 s): sensors below 10 Hz then sat out most framesets (5-10 Hz: 91 % of "
                           "the lab's framesets rejected; docs/accuracy.md, Session 10)")
    wait: float = Field(0.75, ge=0, description="s of data time to wait for late messages before a frameset is closed: "
                        "at least max_gap plus the sensors' delays, or a slow sensor's later bracketing message comes "
                        "too late (2-4 Hz sensors with 0.25 s: 10 % of their views not interpolated, 14 % lost)")
    min_views: int = Field(2, ge=2)
    max_stamp_future: float = Field(5.0, gt=0, description="s: messages stamped further ahead of the clock are rejected")
    max_stamp_past: float = Field(30.0, gt=0, description="s: messages stamped further behind the clock are rejected")


class PreprocessConfig(_Section):
    min_confidence: float = Field(0.6, ge=0, le=1)
    partial_torso: bool = Field(
        True, description="a detection needs a shoulder and a hip at min_confidence, one side may be hidden (a "
        "person seen in profile hides the far shoulder and hip behind the body); false: all four, as the paper. "
        "Such a view only follows a hypothesis of whole views, where its camera had two cycles and its seen torso "
        "joints meet the hypothesis' within associate.gate_pixels (its depth is unbounded from below: it would "
        "pair with anyone along its ray); a pair of two whole views that it rivals (one camera sees someone else "
        "in profile nearer the other's person) is not made; the bootstrap's pairs take whole views only. The "
        "lab from no initial estimate was within 0.05 m / 0.5° on 4 of 5 seeds, not 3 (its cam_13 sees people "
        "side-on: 0.119 m -> within 0.025 m), a hall of 30 cameras 0.0133 -> 0.0124 m shape (docs/bootstrap.md, "
        "Sessions 47-49)")
    confidence_reference: float | None = Field(
        0.9, gt=0, le=1, description="the 90th percentile of a sensor's detected torso-joint confidences that "
        "min_confidence is stated for (the paper's detector; the simulator's run 0.93-0.98). A detector's scores "
        "are its own scale: a sensor whose run lower has its confidences scaled up to it (at most x3, once "
        "200 of its torso joints were seen), so the threshold and the confidence noise model mean the same for "
        "every detector. With 0.7x the simulator's scores the lab ended 0.08 m off (a camera left at its start), "
        "with 0.6x it stayed at its start; now 0.028 m as unscaled (docs/accuracy.md, Session 15). None: "
        "confidences taken as they are")
    min_box_distance: float = Field(0.03, ge=0, description="fraction of the image diagonal: persons whose boxes are "
                                    "closer are dropped (their keypoints mix). The paper's 100 px at 848x480 (0.1) "
                                    "dropped 88 % of the persons with 4 walkers in a 7 x 5 m room and left cameras "
                                    "unplaced; 0.03 (29 px) calibrates that room to 0.8 cm and the lab as before "
                                    "(docs/bootstrap.md, Session 7)")
    duplicate_distance: float = Field(
        0.1, ge=0, description="fraction of a person's size in the image: a detection whose joints at "
        "min_confidence lie on another's (80 % of the joints both have within this of each other, at least 3 "
        "and half of the smaller one's) is the same person detected twice, as top-down detectors do when two "
        "boxes on one person survive their non-maximum suppression; the one with fewer (less confident) joints "
        "is dropped (counted `duplicate`) before the crowd and the min_box_distance checks, which would drop "
        "both. A detector that sent every person twice left the lab from no initial estimate with nothing to "
        "start from (docs/accuracy.md, Session 54). 0: off")
    max_persons: int = Field(10, ge=1)
    pixel_sigma: float = Field(2.0, gt=0, description="px: keypoint noise at confidence 1 when a message has no covariance")
    min_pixel_sigma: float = Field(0.5, gt=0, description="px: floor of a joint's std from a message's covariance: "
                                   "no detector places a joint better, and a zero variance (sent as a placeholder) "
                                   "would make a joint an exact measurement that no pose can meet: from a "
                                   "0.25 m / 10° start the lab stayed at its start")
    pixel_reference: tuple[PositiveInt, PositiveInt] | None = Field(
        (640, 480), description="image size (width, height) for which every px parameter of the engine is stated "
        "(PIXEL_FIELDS): each is multiplied by the square root of the cameras' median image area (of their keypoint "
        "messages: the initial estimate's resolution, else the intrinsics') over this one's, "
        "since a detector's pixel errors grow with the image (a 1920x1080 network: x2.4). The default is VGA, the "
        "lab's median camera. None: the px values are taken as they are (EngineConfig.for_images)")

    @field_validator("confidence_reference", "pixel_reference", mode="before")
    @classmethod
    def _none(cls, v: Any) -> Any:
        # TOML has no null: `--set preprocess.confidence_reference=none` turns it off
        return None if isinstance(v, str) and v.strip().lower() in ("none", "null", "off") else v


class AssociateConfig(_Section):
    min_height: float = Field(1.70, gt=0, description="m, smallest person expected")
    max_height: float = Field(2.00, gt=0, description="m, tallest person expected")
    hips_ratio: float = 0.1526
    shoulders_ratio: float = 0.1753
    torso_ratio: float = 0.2924
    depth_margin: float = Field(0.15, ge=0, description="relative widening of the depth interval")
    max_distance: float = Field(1.0, gt=0, description="m, closest-point distance threshold between segments")
    min_views: int = Field(2, ge=2)
    epipolar_sigmas: float = Field(4.0, ge=0, description="a hypothesis of two views whose joints miss each other's "
                                   "epipolar lines by more than this many keypoint stds (median over the joints), plus "
                                   "2 stds of the two poses' uncertainty (Pipeline._pose_px), pairs two people: dropped (two views have no "
                                   "third to show it; docs/accuracy.md, session 12). 0: off")
    reassociate: bool = Field(True, description="once cameras are certain, gate hypotheses by reprojection error")
    gate_pixels: float = Field(25.0, gt=0, description="px, a view whose torso reprojects further is split off")
    min_views_unsettled: int = Field(3, ge=2, description="views a hypothesis needs while one of its cameras is unsettled: "
                                     "a wrong view among 3 shows as a residual, between 2 it cannot")
    settled_cycles: int = Field(3, ge=0, description="cycles after which a camera counts as settled")
    relocalize: bool = Field(True, description="a camera whose detections stop joining hypotheses is re-localised by PnP "
                             "against persons the others triangulate; a pose beyond 6 sigma of the initial estimate "
                             "(its uncertainty) is refused: a lone detection may be the other person")
    relocalize_px: float = Field(8.0, gt=0, description="px: a re-localisation's PnP inlier threshold")
    relocalize_interval: float = Field(10.0, gt=0, description="s of data time between checks for lost cameras")
    relocalize_after: int = Field(10, ge=0, description="cycles before the first check: early on every camera associates poorly")
    lost_ratio: float = Field(0.15, ge=0, le=1, description="a camera is lost when less than this share of its detections is associated ...")
    lost_min_detections: int = Field(30, ge=1, description="... out of at least this many (decayed by half at each check)")


class SelectConfig(_Section):
    scope: int = Field(50, ge=1, description="hypotheses per cycle")
    min_spacing: float = Field(0.2, ge=0, description="m between centres of mass within one cycle")
    queue_size: int = Field(5000, ge=10)
    newer_bias: float = Field(3.0, ge=0, description="selection weight grows as exp(bias * age rank in [0, 1])")
    interval: float = Field(0.5, gt=0, description="s of data time between cycles")
    first_scope: int = Field(150, ge=0, description="hypotheses of the first cycle, which waits until the queue holds "
                             "that many with associate.min_views_unsettled views, min_spacing apart, or first_wait has passed: from a rough "
                             "start a few wrong associations outweigh a cycle's worth of data and drag cameras metres "
                             "off; many hypotheses outvote them (0 = the first cycle is like any other)")
    first_wait: float = Field(20.0, ge=0, description="s of data time after the first hypothesis that the first cycle waits at most")
    first_passes: int = Field(2, ge=1, description="passes of the first adjustment, each re-associating every frame so far "
                              "with the last pass's estimate")
    first_gate: float = Field(40.0, ge=0, description="χ² (6 dof, ~6 σ): a camera a pass of the first adjustment puts "
                              "further than this from its prior (the initial estimate and its std) keeps its start: "
                              "wrong associations of a rough start, not the data, move a camera that far; unless most "
                              "cameras went that far (then the stated std is wrong). 0: off")
    cycle_gate: float = Field(40.0, ge=0, description="χ² (6 dof): a cycle that puts a camera further than this from "
                              "its predicted state (the filter's pose and covariance) is not taken for it: in a crowd "
                              "a run of wrong associations drags a camera off faster than its uncertainty allows (6 "
                              "walkers: a camera 1.6 m off, docs/accuracy.md, Session 11); it keeps its pose, its "
                              "uncertainty grows by the process noise, and later cycles associate it again. Unless "
                              "most cameras the cycle moved went that far. 0: off")
    first_cycle_gate: float = Field(16.0, ge=0, description="χ² (6 dof, p ≈ 0.014): a camera no cycle or adjustment has "
                                    "calibrated yet, which a cycle would move further than this from its prior on fewer "
                                    "than first_cycle_observations projections, keeps its start: a few views of a camera "
                                    "still at its rough start are the likeliest wrong associations (a camera put 0.85 m / "
                                    "28° off by 3 views, docs/accuracy.md, Session 16); a cycle with more of its views "
                                    "decides. 0: off")
    first_cycle_observations: int = Field(100, ge=0, description="projections of a not yet calibrated camera that let a "
                                          "cycle move it beyond first_cycle_gate")
    dispute_cycles: int = Field(5, ge=0, description="cycles in a row that refuse a camera's move (cycle_gate) before an "
                                "adjustment over the archived frames it sees someone in, its prior re-opened, decides "
                                "between its estimate and the cycles: either their associations or its stated std is "
                                "wrong (a first adjustment left a camera 13° off with a 2° std and the gate held it "
                                "there, docs/accuracy.md, Session 17); each verdict for the estimate doubles the next "
                                "run needed. 0: off")


class OptimizeConfig(_Section):
    solver: Literal["lm", "dogleg"] = "lm"
    max_iterations: int = Field(50, ge=1)
    robust: Literal["none", "huber", "cauchy"] = "huber"
    robust_k: float = Field(2.0, gt=0, description="robust kernel width in sigmas")
    min_landmark_views: int = Field(2, ge=2)
    min_camera_observations: int = Field(30, ge=1, description="a camera with fewer projections in a cycle is left out of it")
    relative_tolerance: float = Field(1e-5, gt=0, description="LM stops when the error improves by less than this fraction")
    min_triangulation_angle: float = Field(2.0, ge=0, description="deg: landmarks whose rays meet at a smaller angle carry no pose information and are left out")
    outlier_rounds: int = Field(2, ge=0, description="solve, drop views (one person in one camera) that reproject badly, solve again")
    outlier_px: float = Field(15.0, gt=0, description="px: a view whose median joint residual exceeds this (and 4x the median view residual) is an outlier")
    batch_view_check: bool = Field(True, description="before an adjustment over all data, a view that the other views of "
                                   "its hypothesis (>= 3 views) miss by more than the outlier limit plus 3 stds of the "
                                   "poses is dropped (a camera seen little followed two wrong views 1.2 m off; "
                                   "docs/accuracy.md, Session 15)")
    bones: Literal["off", "auto", "batch", "all"] = Field(
        "auto", description="people keep their size: tie the bone lengths of each person's hypotheses to one unknown "
        "length per bone and person (docs/bones.md); 'batch': in the first and the final adjustment (for camera chains "
        "without three-way overlap, e.g. corridors: 0.127 -> 0.051 m there; in the 20-camera lab it cost shape "
        "accuracy, 0.0118 -> 0.0145 m from 0.10 m / 5°); 'auto': in the final adjustment when some camera saw people "
        "only together with one other camera (a chain), else off; 'all': in every cycle too")
    bone_sigma: float = Field(0.02, gt=0, description="m: std of one measured bone length about the person's own "
                                                       "(keypoints are not joint centres; shoulders shrug)")
    floor: bool = Field(True, description="with bones (not in the bootstrap): each hypothesis' lower ankle held to the "
                        "plane of all of them (backend/floor.py): a chain of cameras seen in pairs bends at every link, "
                        "the floor people walk on does not")
    floor_sigma: float = Field(0.05, gt=0, description="m: std of a lower ankle's height about the plane (heel rise, "
                               "where a detector puts the ankle)")
    max_size_ratio: float = Field(1.3, ge=0, description="with bones: a hypothesis whose triangulated body is more "
                                  "than this times the largest person's is two walkers seen by two cameras that share no "
                                  "floor (docs/bones.md, Session 33); it is dropped. 0: off")
    lenses: Literal["off", "auto"] = Field(
        "auto", description="the final batch adjustment (and the split-half check's) also estimates how far each lens "
        "is off its calibration file (focal lengths, principal point), for the cameras that see people together with "
        "two more, when two halves of the data show the lenses off alike (Wilcoxon's test of their estimates' products "
        "at 5 %): an empirical Bayes prior, and none when the lenses are as good as their files (backend/optimize.py, "
        "_lens_prior; docs/accuracy.md, Session 37). The result's poses are then the ones that fit the estimated lenses, "
        "which `extrcal calibrate` writes next to it; the files are not changed")
    lens_focal_std: float = Field(0.02, gt=0, description="the loose prior of the first look at the lenses: std of a "
                                  "focal length about its file's, as a fraction")
    lens_centre_std: float = Field(0.01, gt=0, description="... and of the principal point, in focal lengths")
    lens_accuracy_focal: float = Field(0.003, ge=0, description="how far the calibration files' focal lengths may be "
                                       "off (std, as a fraction) in the stated std (the first adjustment's, then the "
                                       "final batch's): each pose's "
                                       "std then carries what such lens errors would move it (a 0.3 % focal length moves "
                                       "a camera 1.5 cm along its view of people 5 m away), not only the keypoints' "
                                       "noise. Lenses the final batch estimates (lenses) carry their own. 0 (with "
                                       "lens_accuracy_centre 0): the std given the lenses as their files")
    lens_accuracy_centre: float = Field(0.003, ge=0, description="... and the principal point (std, in focal lengths: "
                                        "2 px for a focal length of 600 px)")


class FloorFrame(_Section):
    """How a bootstrap defined the world frame by the floor (``bootstrap.floor_frame``):
    origin on the floor under ``first``, x towards the floor point under ``second``, the
    floor ``ankle_height`` m below the people's lower ankles' plane."""

    first: str
    second: str
    ankle_height: float = Field(ge=0)


class RefineConfig(_Section):
    initial_std_translation: float = Field(0.25, gt=0, description="m: how far the initial estimate may be off (its std; "
                                           "the paper uses 0.025, which makes the filter creep from worse starts)")
    initial_std_rotation: float = Field(10.0, gt=0, description="deg (paper: 1)")
    filter_std_translation: float = Field(0.025, gt=0, description="m: process noise unit of the Kalman cycles (paper's initial std)")
    filter_std_rotation: float = Field(1.0, gt=0, description="deg")
    process_noise: float = Field(0.05, ge=0, description="fraction of the initial std added per cycle")
    keep_scale: bool = Field(True, description="similarity-align to the initial estimate and keep its scale")
    measurement: Literal["posterior", "marginal"] = Field(
        "posterior",
        description="'marginal': the paper's update with the marginal covariance as noise (counts the prior twice); "
        "'posterior': the data-only information of the cycle",
    )
    converged_translation: float = Field(0.02, gt=0, description="m: a camera is converged when it moved less than this over the last converged_cycles cycles ...")
    converged_rotation: float = Field(0.2, gt=0, description="deg ... and turned less than this ...")
    converged_std_translation: float = Field(0.03, gt=0, description="m ... and its std is below this ...")
    converged_std_rotation: float = Field(0.5, gt=0, description="deg ... and this (after the final batch adjustment, which "
                                          "uses all data at once, the std alone decides)")
    converged_cycles: int = Field(10, ge=1, description="cycles over which the net pose change is measured")
    final_batch: bool = Field(True, description="a batch adjustment over all frames, re-associated with the final estimate, when the run stops")
    floor_frame: FloorFrame | None = Field(None, description="set by the bootstrap's hand-over (bootstrap.level_final): "
                                           "the world frame is the floor's, made this way; the final batch adjustment's "
                                           "floor (all the data's people) levels it again")
    batch_size: int = Field(1000, ge=10, description="most hypotheses in the final batch adjustment")
    batch_fill: bool = Field(True, description="the final batch takes the hypotheses select.min_spacing / 2 apart first, "
                             "then the others up to batch_size (false: the spaced ones only; a walker who passes the "
                             "same spots again, as along a corridor, then loses most of a chain's links)")
    final_batch_from_start: bool = Field(False, description="the final batch also from the start (the bootstrap's "
                                         "estimate: set by the hand-over), kept when it explains at least as many "
                                         "observations at a lower cost per observation")
    final_batch_from_data: bool = Field(True, description="a run from an initial estimate that the bootstrap checked "
                                        "(bootstrap.with_initial) and kept: the final batch also from the data's shape "
                                        "where the two disagree on a camera (beyond bootstrap.agree_* or 3x the "
                                        "bootstrap's std): held to the data's shape by the hand-over's prior where the "
                                        "estimate lies beyond hold_gate of it, kept when the result stays within it and "
                                        "explains at least as many observations; else with the initial estimate's prior, "
                                        "kept when it explains at least as many observations at a lower cost per "
                                        "observation")
    hold_gate: float = Field(16.8, gt=0, description="χ² (6 dof, p 0.01) of a camera's pose against the hand-over's "
                             "prior at the data's shape (final_batch_from_data): the estimate beyond it on some camera "
                             "tries the batch held there; that batch is kept only with every camera within it")
    archive_frames: int = Field(10000, ge=100, description="preprocessed framesets kept for re-localisation and the final batch")
    split_check: bool = Field(True, description="after the final batch, solve it again on each of two halves of the "
                              "frames (alternate split_block s) and compare: a camera the halves place further apart "
                              "than their own stds allow gets its std widened to what the data show (backend/"
                              "split_check.py; costs about one more final batch)")
    split_block: float = Field(10.0, gt=0, description="s: the blocks of frames the two halves alternate")
    split_ratio: float = Field(2.5, gt=1, description="widen a camera's std when the halves' difference / sqrt(3) "
                               "exceeds this many times the root sum of squares of the halves' stds (honest stds: "
                               "below 2 nearly always)")


class MonitorConfig(_Section):
    """Cameras that move after they converged (backend/monitor.py, docs/monitor.md)."""

    enabled: bool | Literal["live"] = Field(
        "live", description="watch converged cameras, flag those the data say moved and calibrate them again; "
        "\"live\" (the default): in the service's sessions (extrcal serve, extrcal demo), not offline (extrcal "
        "calibrate, the benches), where a camera rarely moves within a recording and the watch's hold of converged "
        "cameras costs an ordinary calibration about a tenth of its shape accuracy (docs/monitor.md)")
    start_fraction: float = Field(0.6, ge=0, le=1, description="share of the calibrated cameras that must have converged "
                                  "before the watch begins (1: the session converged)")
    bin_seconds: float = Field(5.0, gt=0, description="s of data per resection of a watched camera (one sample of the change test)")
    min_points: int = Field(100, ge=12, description="joints a bin needs to count")
    max_bin_seconds: float = Field(20.0, gt=0, description="s: a bin short of min_points stays open for more grid steps "
                                   "(a camera that sees little), its data older than this dropped")
    window_seconds: float = Field(60.0, gt=0, description="s: a change is looked for this far back")
    min_change_bins: int = Field(2, ge=1, description="bins after a change before it is flagged, with any one "
                                 "of them left out (so one more than this)")
    reference_seconds: float = Field(180.0, gt=0, description="s of the camera's own bins before a change it is compared with")
    min_reference_bins: int = Field(12, ge=3, description="bins a camera needs before the change test runs")
    short_reference_bins: int = Field(4, ge=2, description="a change early in a camera's first watch, with fewer than "
                                      "min_reference_bins bins before it but at least this many, is tested once the camera "
                                      "has min_reference_bins bins in all, against the scatter of its bins about their "
                                      "means on both sides of it (a camera bumped early in its watch was otherwise never "
                                      "flagged, and held where it was); min_reference_bins or more: not tested")
    where_covariates: bool = Field(True, description="a step must also show with the bias of each bin that where its "
                                   "points were in the image explains (linear in their mean position): a lens a little off "
                                   "its calibration, or keypoints off the joints, bias a camera's data-only pose by where "
                                   "the people are in its view, and people moving to another part of it is no move")
    lens_covariates: bool = Field(True, description="... and with the bias a lens off its calibration file (focal lengths, "
                                  "principal point) gives each bin's pose, which depends on where and how deep its points "
                                  "were; the lens's error fitted with the step (prior std lens_std)")
    lens_std: float = Field(0.02, gt=0, description="the lens's relative error the test allows for a priori (of the focal "
                            "length; the principal point's shift as a fraction of it)")
    odd_bin_level: float = Field(0.05, gt=0, lt=1, description="a step must pass without any one of the bins after "
                                 "it, and without more when the camera's own reference has odd bins (beyond the 99th "
                                 "percentile about its mean) so often that more than one among those after it is likelier "
                                 "than this (binomial): lenses a little off and keypoints off the joints make a camera's "
                                 "bins odd now and then, and two odd ones after a split are no move")
    bin_std_translation: float = Field(0.05, ge=0, description="m: most error of one bin's resection that its information does "
                                       "not show (where the people were, the others' own errors); the share added to each bin's "
                                       "covariance is measured on the camera's own bins")
    bin_std_rotation: float = Field(0.5, ge=0, description="deg")
    model_std_translation: float = Field(0.002, ge=0, description="m: drift of a camera's data-only pose that more data do not "
                                         "remove (the others' estimates wander): a floor of the test's covariance")
    model_std_rotation: float = Field(0.02, ge=0, description="deg")
    chi2: float = Field(40.0, gt=0, description="significance of a change (6 dof; 40 ≈ p 1e-6)")
    min_translation: float = Field(0.015, ge=0, description="m: ... and its size, translation ...")
    min_rotation: float = Field(0.3, ge=0, description="deg ... or rotation, that flag a converged camera as moved")
    recalibrate_seconds: float = Field(60.0, gt=0, description="s of data since the change a flagged camera is calibrated "
                                       "again from (one resection over all of it every bin, the others fixed)")
    recalibrate_every: float = Field(20.0, gt=0, description="s of data between the flagged camera's adjustments over all "
                                     "its data since the change, from recalibrate_seconds to twice that (the last): its "
                                     "pose is held in between, so the pose two minutes after a move is from the latest")
    hold: bool = Field(True, description="watched cameras keep their pose: the cycles calibrate only the others (and a moved "
                       "camera against them); a calibrated camera changes when the monitor finds it moved, not by the "
                       "cycles' noise or a moved camera's pull before it is found")
    process_noise: float = Field(0.0, ge=0, description="without hold: the filter's process noise of a watched camera, as a "
                                 "fraction of refine.process_noise: a calibrated camera does not drift, the monitor catches moves")
    reopen_std_translation: float = Field(0.10, gt=0, description="m: the flagged camera's uncertainty from then on")
    reopen_std_rotation: float = Field(5.0, gt=0, description="deg")

    @property
    def on(self) -> bool:
        """Whether the pipeline watches: ``"live"`` is on only once ``EngineConfig.live()``
        made it true (the service's sessions)."""
        return self.enabled is True


class BootstrapConfig(_Section):
    """Calibration without an initial estimate (backend/bootstrap.py, docs/bootstrap.md)."""

    max_seconds: float = Field(120.0, ge=0, description="s of data the bootstrap of `extrcal calibrate` uses (0: the whole recording)")
    min_pair_frames: int = Field(30, ge=8, description="frames a camera pair needs in which each sees one person, the same one")
    pair_min_moving: int = Field(10, ge=0, description="of a pair's agreeing frames, at least this many in which its "
                                 "person moved since the last one that did (pair_motion): a person standing still gives "
                                 "the same few points again, and two people each standing still in one of two cameras "
                                 "that share no view agree with a wrong pose in every frame")
    pair_motion: float = Field(0.15, gt=0, description="... moved in either view by this times the person's size there "
                               "(the joints' median displacement over their median distance from their centre)")
    ransac_px: float = Field(3.0, gt=0, description="px: RANSAC threshold (Sampson error) of a pair's essential matrix")
    frame_px: float = Field(4.0, gt=0, description="px: a frame is a pair's correspondence when its joints' median Sampson error is below this")
    min_consistent_ratio: float = Field(0.3, ge=0, le=1, description="share of a pair's single-person frames that must agree with its geometry")
    min_triangulation_angle: float = Field(3.0, ge=0, description="deg: median angle between a pair's rays; below it the baseline is unknown")
    min_shared_points: int = Field(40, ge=5, description="joints two pairs triangulate at the same instants to relate their scales")
    bone_scales: bool = Field(True, description="pairs that no shared joints relate (a camera chain without three-way "
                              "overlap, e.g. a corridor) are related by the median bone lengths of the people each "
                              "pair sees, and the bootstrap's adjustments then hold the people's bones (with "
                              "optimize.bones 'auto'); off: such a chain places only its best-related pairs")
    rotation_outlier: float = Field(5.0, gt=0, description="deg: a pair disagreeing more with the averaged rotations is dropped")
    split_ratio: float = Field(0.5, ge=0, description="a camera whose pairs that disagree with the averaged rotations agree "
                               "in at least this share of the frames its other pairs agree in is split between two "
                               "poses (two walkers who moved alike): no pair places it; the resection may (0: off)")
    bridge_spread: float = Field(2.0, ge=0, description="a bridge pair (one no cycle of pairs checks) whose person changes "
                                 "size from frame to frame by more than this many times the pairs' median spread (and "
                                 "by more than 13 %) saw two people, not one: it is dropped (docs/bones.md, Session 33). "
                                 "0: off")
    check_min_frames: int = Field(10, ge=3, description="a camera reached only over bridge pairs is checked against "
                                  "the persons the other cameras triangulate when this many of them (outside its pairs' "
                                  "frames) lie in its view while it sees one person (else kept unchecked)")
    check_min_agree: float = Field(0.5, ge=0, le=1, description="share of those frames in which its detection must be "
                                   "that person (within check_px) to pass; else it is re-localised by PnP or not placed")
    check_px: float = Field(8.0, gt=0, description="px: median reprojection error of an agreeing frame's joints")
    resect: bool = Field(True, description="cameras no pair placed are resected (PnP) against the persons the placed "
                         "cameras triangulate (backend/resect.py)")
    resect_px: float = Field(8.0, gt=0, description="px: a frame agrees with a resected pose when a detection lies this close "
                             "to a triangulated person's projection (median over joints)")
    resect_min_frames: int = Field(20, ge=6, description="agreeing frames a resected camera needs")
    resect_min_share: float = Field(0.3, ge=0, le=1, description="share of the frames with a person in its view (while it "
                                    "sees somebody) that must agree")
    resect_min_spread: float = Field(0.3, ge=0, description="m: the agreeing persons' spread over the floor (2nd principal "
                                     "std of their centres): a person at one spot leaves the pose poorly determined")
    resect_ambiguity: float = Field(0.5, ge=0, description="no clearly different pose (10°, 0.5 m) may agree in more than "
                                    "this share of the frames the best one agrees in")
    join_groups: bool = Field(True, description="cameras no pair links to the placed ones (two rooms joined by a door: "
                              "where a camera in each sees one person, it is a different one) are bootstrapped on their "
                              "own and joined as one body by the persons each group sees of the other's (backend/groups.py; "
                              "the resection's guards, resect_*, pooled over the group's cameras)")
    late: bool = Field(True, description="cameras the bootstrap did not place are resected again (same guards) against "
                       "the online estimate over all data when the run ends, and join its final batch adjustment "
                       "(backend/late_join.py) ...")
    late_join_interval: float = Field(30.0, ge=0, description="... and while it runs, every this many s of data (after the "
                                      "first adjustment, when they have new framesets): a camera placed joins the "
                                      "running pipeline, whose cycles then calibrate it (0: only when the run ends)")
    late_pairs: bool = Field(True, description="a camera those resections do not place may be placed by its pair with a "
                             "placed camera (the bootstrap's pair guards; the baseline's length from the floor both "
                             "sides' people stand on, else their bones): the end of a camera chain, which only its "
                             "neighbour sees with it")
    level_final: bool = Field(True, description="the world frame is levelled again on the floor of the final batch "
                              "adjustment's people (the bootstrap's floor is that of the cameras it placed: when it "
                              "placed only one pair and the rest joined later, that pair's people's floor tilted the "
                              "frame 12° along a corridor)")
    batch_rounds: int = Field(3, ge=1, description="bundle adjustments, each re-associating all frames with the previous result")
    batch_hypotheses: int = Field(800, ge=10, description="most hypotheses per bundle adjustment")
    prior_std_translation: float = Field(1.0, gt=0, description="m: the weak prior of the bundle adjustment (a gauge, not information)")
    prior_std_rotation: float = Field(10.0, gt=0, description="deg")
    handover_std_translation: float = Field(
        0.03, gt=0, description="m: least std the online pipeline starts from (3x the bootstrap's own std if larger). "
        "A looser prior lets the first adjustment follow wrong associations away from the data's shape: two rooms "
        "joined by a door, four walkers, no initial estimate, shape 0.0387 m with 0.10 m / 2° against 0.0129 m; the "
        "other layouts and the lab the same either way (docs/accuracy.md, Session 56)")
    handover_std_rotation: float = Field(0.5, gt=0, description="deg")
    height_mean: float = Field(1.72, gt=0, description="m: population prior of adult height (mixed sexes; docs/bootstrap.md)")
    height_std: float = Field(0.10, gt=0, description="m: its spread between persons")
    ratio_std: float = Field(0.02, ge=0, description="relative spread between persons of leg + torso length / height")
    with_initial: Literal["auto", "always", "never"] = Field(
        "auto", description="with an initial estimate (`extrcal calibrate --initial`): bootstrap too, align the data's "
        "shape onto the initial estimate (its frame and scale kept) and start the online pipeline there; 'auto': only "
        "when the initial estimate is further off the data than its stated std says (auto_sigma) or than the paper's way "
        "copes with (auto_translation, auto_rotation, auto_displacement), 'never': the paper's way "
        "(backend/reconcile.py)")
    initial_scale: Literal["auto", "keep", "combine", "people"] = Field(
        "auto", description="with an initial estimate, the result's scale is checked against the people's (known "
        "heights, else the population prior; backend/scale_check.py): 'keep' reports the check and keeps the initial "
        "estimate's scale (the paper's protocol), 'combine' corrects it to the inverse-variance mean of the two, "
        "'people' to the people's; 'auto': 'combine' when the walkers' heights are known, else 'keep'. A correction "
        "the two disagree on by more than refuse_sigma of their joint std is not made")
    agree_translation: float = Field(0.05, ge=0, description="m: a camera of the initial estimate agrees with the data when "
                                     "its centre is within this (or 3x the bootstrap's std) of the aligned bootstrap's ...")
    agree_rotation: float = Field(0.5, ge=0, description="deg ... and its orientation within this (or 3x the std)")
    auto_sigma: float = Field(1.5, gt=0, description="with_initial='auto' starts from the data's shape when the initial "
                              "estimate's RMS distance from it exceeds this many of its stated std (refine.initial_std_*)")
    auto_translation: float = Field(0.375, gt=0, description="m: ... and whatever its stated std, when that RMS distance "
                                    "exceeds this (or auto_rotation): from further off, the paper's first adjustments lose "
                                    "cameras even when told the std honestly (the association cuts rays to depth intervals "
                                    "about a person wide; lab from 0.75 m / 20° stated as such: 0.19 m / 0.15 m on 2 of 3 "
                                    "seeds against 0.02 m / 0.07 m from the data's shape)")
    auto_rotation: float = Field(15.0, gt=0, description="deg")
    auto_displacement: float = Field(1.5, gt=0, description="m: ... or when the initial estimate's errors move what its "
                                     "cameras see by more than this at their persons' distance (the typical camera's "
                                     "centre error plus its turn times the median distance of its persons): the "
                                     "association pairs rays that pass within max_distance (1 m) at the persons. "
                                     "Measured: the lab from 0.25 m / 10° 1.2 m, the paper's way at the limit; from "
                                     "0.35 m / 15° 1.8 m, it copes (seed 0 0.035 m shape, the limit 0.030 m); a warehouse "
                                     "(persons 9-16 m away) from 0.25 m / 8° and 10°: 1.7 and 2.1 m, a camera 16° and "
                                     "5 m off (docs/bootstrap.md, Session 52)")
    refuse_sigma: float = Field(6.0, gt=0, description="a bootstrap pose further from the initial estimate than this many "
                                "of its stated std (refine.initial_std_*), or of the cameras' lower quartile distance when "
                                "that is larger, is not used: one of the two is grossly wrong")
    live_check: bool = Field(True, description="live service: a session with an initial estimate (not told "
                             "distrust_initial) checks it against the data once, after max_seconds of data (again "
                             "live_interval later while the data do not allow it, three tries): a "
                             "bootstrap on the archived frames, reconciled as with_initial says; when the data's shape "
                             "is to be used (the estimate rougher than it states or than auto_translation / "
                             "auto_rotation, or cameras swapped), the session goes on from there with every frame "
                             "archived (the solver pauses the cycles while the bootstrap runs)")
    live_first: float = Field(60.0, gt=0, description="live service (backend/live_bootstrap.py): s of data before the "
                              "first bootstrap attempt of a session without an initial estimate")
    live_interval: float = Field(30.0, gt=0, description="s of data between attempts (until one is accepted)")
    live_min_placed: float = Field(0.9, ge=0, le=1, description="an attempt before max_seconds of data is accepted when it "
                                   "placed this share of the cameras that saw people in min_pair_frames framesets; "
                                   "from max_seconds on any result that places cameras is")
    live_confirm: bool = Field(True, description="... and only when the attempt before it agrees: every camera both "
                               "placed within live_confirm_translation / live_confirm_rotation after a similarity "
                               "alignment (a camera chained wrongly over a bridge pair, 160° off in the lab at 60 s, "
                               "is rarely chained the same way with more data)")
    live_confirm_translation: float = Field(0.25, gt=0, description="m (the bootstrap's own precision is 0.01-0.04 m)")
    live_confirm_rotation: float = Field(5.0, gt=0, description="deg (its own: 0.1-0.8°)")

    def handover_std(self, std_m: float, std_deg: float) -> tuple[float, float]:
        """(m, deg) the prior std of a camera started from the data's shape: 3x the
        bootstrap's own std ``std_m`` / ``std_deg`` (NaN counts as 0), or the
        ``handover_std_*`` floor where that is more."""
        st, sr = (0.0 if math.isnan(x) else float(x) for x in (std_m, std_deg))
        return max(self.handover_std_translation, 3 * st), max(self.handover_std_rotation, 3 * sr)


class ClockConfig(_Section):
    """Sensor clock offsets estimated from the data (backend/clock_offsets.py, docs/clock_offsets.md)."""

    estimate: bool | Literal["auto"] = Field(
        "auto", description="estimate each sensor's clock offset from its keypoints and apply confident ones beyond NTP's "
        "spread (the service runs the estimate in a thread; docs/clock_offsets.md). It costs CPU (live: 0.16 -> 0.31 cores "
        "for 20 cameras at 30 Hz, 0.61 -> 1.13 for 100, the loop's p99 lag 31 -> 301 ms), so \"auto\" (the default) starts "
        "it only once a sensor's stamps run more than auto_lead apart from the others' as they arrive; true: from the "
        "start; false: never")
    auto_lead: float = Field(0.06, gt=0, description="s: with estimate = \"auto\", the median over 10-60 s of a sensor's "
                             "newest stamp minus the median of all sensors' newest stamps (sampled every 0.5 s of data) "
                             "beyond which estimation starts (synchronised sensors: within 30 ms, their network delays and "
                             "frame rates; docs/clock_offsets.md, Session 17)")
    max_offset: float = Field(0.25, gt=0, le=2.0, description="s: largest offset searched (relative to the synchronised clock)")
    interval: float = Field(10.0, gt=0, description="s of data time between estimates")
    settled_interval: float = Field(60.0, ge=0, description="s: a synchronised sensor (nothing applied, "
                                    "its estimate within half of min_apply) whose fresh estimates agree is estimated at "
                                    "twice the interval of the last time, up to this (CPU; a drift is then seen within it)")
    block: float = Field(5.0, gt=0, description="s of data per block: the unit of the jackknife (longer than the detector's correlated noise)")
    window: float = Field(120.0, gt=0, description="s of recent data an estimate uses (follows slow drift)")
    track_gap: float = Field(0.3, gt=0, description="s: longest gap bridged within a person's track")
    coarse_step: float = Field(0.01, gt=0, description="s: grid step of the search over the full range")
    coarse_nuisance: Literal["fixed", "pose"] = Field("fixed", description="the sensor's pose in that search: held at its "
                                                      "current estimate ('fixed'), or fitted at every candidate ('pose': "
                                                      "a pose shift can mimic a time shift, the profile flattens)")
    fine_step: float = Field(0.004, gt=0, description="s: grid step around a found offset (a parabola through it measures the minimum)")
    fine_half: float = Field(0.02, gt=0, description="s: half-width of that grid")
    match_px: float = Field(40.0, gt=0, description="px: a track of a sensor not in a hypothesis is that person only when it fits within this (median over joints) ...")
    match_sigmas: float = Field(3.0, ge=0, description="... widened by this many stds of the person's projection under the "
                                "sensor's pose covariance (a mistimed sensor is also badly calibrated) ...")
    match_max_px: float = Field(120.0, gt=0, description="... up to this (px)")
    view_match_px: float = Field(10.0, gt=0, description="px: a hypothesis' view is a track's detection when they are "
                                 "this close (median over joints)")
    min_blocks: int = Field(4, ge=3, description="blocks of data a sensor needs for an estimate")
    reference_spread: bool = Field(True, description="the estimate at the end of a run (after the final adjustment) also "
                                   "measures how far each offset moves with the cameras that place the persons it is "
                                   "timed against (each left out in turn; an error they share is invisible to the "
                                   "jackknife over blocks of data): the std reported is the larger of the two. CPU: a "
                                   "fine search per such camera and sensor (20 cameras: some 20 s of CPU more at the end)")
    min_scale_px: float = Field(0.5, gt=0, description="px: floor of the robust residual scale (median distance) of a sensor's fit")
    max_scale_px: float = Field(12.0, gt=0, description="px: no estimate while a sensor's fit is worse than this (the poses have not settled)")
    max_std: float = Field(0.01, gt=0, description="s: an offset is applied once its std is below this ...")
    min_apply: float = Field(0.015, ge=0, description="s: ... and it is larger than this (and 3 std): below this NTP does the "
                             "job (a working NTP keeps a LAN's clocks within a few ms; 15 ms of mistiming moves a walking "
                             "person by 2 cm, below the 3D noise of the detections), and once an offset is applied the "
                             "sensor's archived views timed with another are left out of the batch adjustments; an "
                             "applied offset is taken back when the estimate falls below half of this")
    min_change: float = Field(0.003, ge=0, description="s: an applied offset is changed when the estimate moved by more than "
                              "this and 2.5 std")
    drift_warning: float = Field(0.01, gt=0, description="s: warn when a sensor's estimate moves by more than this")
    retime_tolerance: float = Field(0.005, ge=0, description="s: when a new offset is applied, archived views timed with one "
                                    "further off are dropped from the final batch ...")
    retime_seconds: float = Field(300.0, ge=0, description="s: ... unless the raw messages of these last seconds can "
                                  "time them again with the final offset (kept per sensor while `estimate` is on; "
                                  "memory: 0.5 kB per message pickled, 33 MB for 180 s of the 20-camera lab)")


class EngineConfig(_Section):
    sync: SyncConfig = SyncConfig()
    preprocess: PreprocessConfig = PreprocessConfig()
    associate: AssociateConfig = AssociateConfig()
    select: SelectConfig = SelectConfig()
    optimize: OptimizeConfig = OptimizeConfig()
    refine: RefineConfig = RefineConfig()
    monitor: MonitorConfig = MonitorConfig()
    bootstrap: BootstrapConfig = BootstrapConfig()
    clock: ClockConfig = ClockConfig()

    @staticmethod
    def from_dict(d: dict[str, Any], source: str = "config") -> "EngineConfig":
        try:
            return EngineConfig.model_validate(d)
        except ValidationError as e:
            raise ConfigError(source, _describe(e)) from None

    @staticmethod
    def load(path: str | Path | None, overrides: list[str] | None = None) -> "EngineConfig":
        d: dict[str, Any] = {}
        if path is not None:
            try:
                d = tomllib.loads(Path(path).read_text())
            except FileNotFoundError:
                raise ConfigError(str(path), "file does not exist") from None
            except tomllib.TOMLDecodeError as e:
                raise ConfigError(str(path), f"not valid TOML: {e}") from None
        for item in overrides or []:
            apply_override(d, item)
        return EngineConfig.from_dict(d, str(path or "overrides"))

    def for_images(self, sizes: Iterable[tuple[int, int]]) -> "EngineConfig":
        """This config with its px parameters (PIXEL_FIELDS) in the pixels of cameras of
        these image sizes (width, height; 0 = unknown): multiplied by the square root of
        their median area over ``preprocess.pixel_reference``'s, which becomes None, so
        that a config already scaled is returned as it is: every entry point that meets
        the cameras (the pipeline, the bootstrap) calls it, and nesting them is harmless.
        Without a known size it is returned as it is too."""
        ref = self.preprocess.pixel_reference
        areas = [float(w) * float(h) for w, h in sizes if w > 0 and h > 0]
        if ref is None or not areas:
            return self
        s = math.sqrt(statistics.median(areas) / (ref[0] * ref[1]))
        d = self.model_dump()
        for section, names in PIXEL_FIELDS.items():
            for name in names:
                d[section][name] *= s
        d["preprocess"]["pixel_reference"] = None
        return EngineConfig.from_dict(d)

    def live(self) -> "EngineConfig":
        """This config as a live session of the service runs it: ``monitor.enabled =
        "live"`` becomes true (everywhere else it counts as false)."""
        if self.monitor.enabled != "live":
            return self
        return self.model_copy(update={"monitor": self.monitor.model_copy(update={"enabled": True})})

    def merged(self, overrides: dict[str, Any]) -> "EngineConfig":
        """A copy with a nested dict of overrides applied (validated)."""
        d = self.model_dump()
        for section, values in overrides.items():
            if isinstance(values, dict) and isinstance(d.get(section), dict):
                d[section].update(values)
            else:
                d[section] = values
        return EngineConfig.from_dict(d)


# every parameter in pixels (at ``preprocess.pixel_reference``), by section
PIXEL_FIELDS: dict[str, tuple[str, ...]] = {
    "preprocess": ("pixel_sigma", "min_pixel_sigma"),
    "associate": ("gate_pixels", "relocalize_px"),
    "optimize": ("outlier_px",),
    "bootstrap": ("ransac_px", "frame_px", "check_px", "resect_px"),
    "clock": ("match_px", "match_max_px", "view_match_px", "min_scale_px", "max_scale_px"),
}


class ConfigError(ValueError):
    def __init__(self, source: str, reason: str):
        super().__init__(f"{source}: {reason}")


def apply_override(d: dict[str, Any], item: str) -> None:
    """``section.key=value`` (value parsed as TOML, else a string) into a nested dict."""
    if "=" not in item or "." not in item.split("=", 1)[0]:
        raise ConfigError("--set", f"expected section.key=value, got {item!r}")
    key, raw = item.split("=", 1)
    section, name = key.strip().split(".", 1)
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    d.setdefault(section, {})[name] = value


def _describe(e: ValidationError) -> str:
    parts = []
    for err in e.errors():
        loc = ".".join(str(x) for x in err["loc"])
        parts.append(f"{loc}: {err['msg']}")
    return "; ".join(parts)
