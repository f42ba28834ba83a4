"""Request and response models: the API's documentation (OpenAPI) and its validation."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from ..session import StopCriteria

MAX_YAML = 4_000_000  # characters; a 1000-camera file is ~200 kB


class SessionCreate(BaseModel):
    """A new session. Camera files come as text (`*_yaml`, the FORMATS.md layouts) or as
    names of files the server was configured with (`camera_files` in service.toml); when
    neither is given the server's `defaults` are used."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{
        "name": "lab, morning",
        "intrinsics_yaml": "cam_0:\n  intrinsics: [610.0, 610.0, 424.0, 240.0]\n  distortion_coeffs: [0, 0, 0, 0, 0]\n  resolution: [848, 480]\n...",
        "initial_yaml": "cam_0:\n  translation: [0, 0, 0]\n  rotation: [0, 0, 0, 1]\n  resolution: [848, 480]\n...",
        "config": {"select": {"scope": 60}},
        "stop": {"converged": True, "duration": 600},
    }]})

    name: str | None = Field(None, max_length=200, description="a label for people")
    intrinsics_yaml: str | None = Field(None, max_length=MAX_YAML, description="intrinsics.yaml text")
    initial_yaml: str | None = Field(None, max_length=MAX_YAML, description="initial extrinsics.yaml text. Without an "
                                     "initial estimate (neither this, `initial` nor a server default) the session "
                                     "bootstraps its start from the people (docs/service.md, docs/bootstrap.md): it "
                                     "collects data (attempts from `bootstrap.live_first` s on, any result from "
                                     "`bootstrap.max_seconds` on), then calibrates in the floor's frame at the "
                                     "people's scale; `bootstrap` in the session shows the phase")
    reference_yaml: str | None = Field(None, max_length=MAX_YAML, description="reference extrinsics to report errors against")
    intrinsics: str | None = Field(None, max_length=200, description="name of a configured intrinsics file")
    initial: str | None = Field(None, max_length=200, description="name of a configured initial estimate")
    reference: str | None = Field(None, max_length=200, description="name of a configured reference")
    config: dict[str, Any] = Field(default_factory=dict, description="EngineConfig overrides by section, e.g. {\"select\": {\"scope\": 60}}")
    stop: StopCriteria = Field(default_factory=StopCriteria, description="when the session ends by itself")
    seed: int = Field(0, ge=0, le=2**32 - 1, description="seed of the hypothesis selection")
    person_height: list[Annotated[float, Field(ge=0.5, le=2.8)]] | None = Field(
        None, min_length=1, max_length=50, description="known height(s) of the walkers in m, e.g. [1.85] or [1.96, "
        "1.70]: the bootstrap's metric scale from them (else from a population prior of adult height); with an "
        "initial estimate, its scale is checked against them when the session stops and corrected as "
        "`bootstrap.initial_scale` says (`scale` in the session)")
    distrust_initial: bool = Field(False, description="bootstrap from the people although an initial estimate is "
                                   "given, then align the data's shape onto it (its frame and scale kept; "
                                   "`bootstrap.with_initial` decides per camera, as `extrcal calibrate`)")


class BootstrapAttempt(BaseModel):
    attempt: int
    data_seconds: float = Field(description="s of data it ran on")
    frames: int = Field(description="framesets it ran on")
    seconds: float = Field(description="wall s it took")
    accepted: bool
    placed: int | None = Field(None, description="cameras it placed")
    needed: int | None = Field(None, description="cameras it had to place to be accepted")
    pairs: int | None = Field(None, description="camera pairs in its view graph")
    error: str | None = Field(None, description="why it was not accepted (too few pairs, too few cameras placed)")


class BootstrapInfo(BaseModel):
    """A session that bootstraps its start from the people (no initial estimate, or
    `distrust_initial`): its phase and progress, and once done where its frame and scale
    come from and which cameras it placed."""

    phase: Literal["collecting", "bootstrapping", "done"] = Field(
        description="collecting framesets; an attempt running; done (handed over to the online pipeline)")
    data_seconds: float = Field(description="s of data collected")
    target_seconds: float = Field(description="bootstrap.max_seconds: from here on any attempt that places cameras is taken")
    next_attempt: float | None = Field(None, description="s of data at which the next attempt runs")
    framesets: int = Field(description="framesets collected (>= 2 views)")
    pairs: int = Field(description="camera pairs that saw one person in bootstrap.min_pair_frames framesets")
    cameras_seen: int = Field(description="cameras that saw people in bootstrap.min_pair_frames framesets")
    attempts: list[BootstrapAttempt] = Field(default_factory=list)
    options: dict[str, Any] = Field(default_factory=dict, description="person_height, distrust_initial as asked")
    placed: list[str] | None = Field(None, description="cameras the bootstrap placed (done)")
    not_placed: list[str] | None = Field(None, description="cameras it could not place: not calibrated (done; once "
                                         "stopped, those the resection then did not place either)")
    frame: str | None = Field(None, description="the world frame of the result (done)")
    scale: dict[str, Any] | None = Field(None, description="metric scale from people: factor, rel_std, method, persons, heights")
    note: str | None = Field(None, description="what the hand-over did")
    reconciled: dict[str, Any] | None = Field(None, description="distrust_initial: the initial estimate vs the data's shape")
    result: dict[str, Any] | None = Field(None, description="the bootstrap's metadata (backend/bootstrap.py)")
    pose_data_seconds: float | None = Field(None, description="s of data from the first message to the first pose")
    pose_wall: float | None = Field(None, description="wall time (epoch s) of the hand-over")
    late: list[str] | None = Field(None, description="cameras it did not place whose framesets are kept beside the online "
                                   "pipeline: resected against its estimate when the session stops (backend/late_join.py)")
    placed_later: list[dict[str, Any]] | None = Field(None, description="(stopped) those placed then and adjusted by the "
                                                      "final batch: name, data_seconds, agreeing frames, spread, prior std")
    late_resections: list[str] | None = Field(None, description="(stopped) each resection's outcome")


class CameraOut(BaseModel):
    name: str
    translation: list[float] = Field(description="optical centre in the world, m")
    rotation: list[float] = Field(description="world_R_cam quaternion [x, y, z, w]")
    std_translation: float | None = Field(description="m, one std (RMS over the axes) of the camera's place in "
                                          "the network's shape, from the solves' covariance, with what the lenses' "
                                          "accuracy adds (optimize.lens_accuracy_*) from the first adjustment on (the "
                                          "final batch's once it ran)")
    std_rotation: float | None = Field(description="deg, as std_translation")
    observations: int = Field(description="keypoint projections of this camera used so far")
    cycles: int = Field(description="cycles this camera took part in")
    change_translation: float | None = Field(description="m, mean pose change per cycle over the last cycles (null before the first)")
    change_rotation: float | None = Field(description="deg")
    converged: bool
    last_seen: float | None = Field(description="stamp of its last accepted message")
    moved_at: float | None = Field(None, description="data time the monitor last found this converged camera moved "
                                   "(bumped): its uncertainty was re-opened and it is calibrated again")
    restarted_at: float | None = Field(None, description="data time this camera last started over from a pose found "
                                       "elsewhere: an adjustment over its archived views found the estimate the cycles "
                                       "kept wrong (a dispute), or it was re-localised")
    restart_reason: str | None = Field(None, description="why it started over, with how far it was off")


SessionStateName = Literal["waiting_for_data", "calibrating", "converged", "stopped", "failed"]


class SessionSummary(BaseModel):
    id: str
    name: str | None = None
    state: SessionStateName
    reason: str
    created_wall: float | None = None
    ended_wall: float | None = None
    cycles: int | None = None
    converged_cycle: int | None = None
    stopped_by: str | None = None
    resumed: int | None = None
    accuracy: dict[str, float | None] | None = Field(None, description="latest errors against the reference (FORMATS.md figures)")


class SessionDetail(SessionSummary):
    """A session with its per-camera estimate. `state` is one of waiting_for_data →
    calibrating ⇄ converged → stopped | failed; `reason` says why it is there."""

    stop: StopCriteria
    config_overrides: dict[str, Any]
    sources: dict[str, str]
    seed: int
    first_data: float | None
    final_batch: dict[str, Any] | None
    live: bool = Field(description="the running session (else read from the state directory)")
    stopping: bool = Field(description="a stop was asked; the final batch adjustment runs")
    storage_error: str | None = Field(None, description="the last write to the state directory failed (running "
                                      "session only); clears when a write succeeds again")
    solver_fault: dict[str, Any] | None = Field(None, description="the optimizer's last failure in the running "
                                                "session: cycle, error, failing (cycles in a row, 0 once it "
                                                "works again), count, recovered_cycle, kept_cycle (the estimate kept)")
    converged: bool
    data_time: float | None
    cameras: list[CameraOut]
    counters: dict[str, Any] | None
    last_cycle: dict[str, Any] | None
    bootstrap: BootstrapInfo | None = Field(None, description="a session that bootstraps: phase, progress, result")
    scale: dict[str, Any] | None = Field(None, description="a session with an initial estimate: person_height as "
                                         "given; once stopped, check: the initial estimate's scale against the "
                                         "people's (people: factor = true metres per metre of the estimate, rel_std, "
                                         "method; initial_rel_std; sigmas apart; mode; factor applied, 1 = kept; "
                                         "refused) and its summary")
    initial_check: dict[str, Any] | None = Field(None, description="a session with an initial estimate "
                                                 "(bootstrap.live_check): phase (running; waiting: to be tried again with more data, or for a clock offset the data found to be applied; done), attempts, data_seconds, used "
                                                 "(the session went on from the data's shape), reconciled (per camera: "
                                                 "the initial estimate's distance from the data's shape, refused, "
                                                 "overruled), note")


class CalibrationCamera(BaseModel):
    translation: list[float]
    rotation: list[float]
    resolution: list[int]
    std_translation: float | None
    std_rotation: float | None
    observations: int
    cycles: int
    change_translation: float | None
    change_rotation: float | None
    converged: bool
    last_seen: float | None


class Calibration(BaseModel):
    """A calibration as JSON: the FORMATS.md extrinsics per camera plus convergence."""

    site: str
    session: str
    state: SessionStateName
    cycle: int | None
    data_time: float | None
    converged: bool | None
    accuracy: dict[str, float | None] | None
    cameras: dict[str, CalibrationCamera]
    version: int | None = Field(None, description="the calibration version shown (null: a running session's live estimate)")
    source_version: int | None = Field(None, description="the version this one copies (an activation), or null")


class CalibrationVersion(BaseModel):
    """One recorded calibration version (GET /calibrations)."""

    version: int
    created: str = Field(description="UTC, ISO 8601")
    by: str = Field(description="who or what recorded it: 'session <id>', 'rollback', 'api'")
    reason: str
    session: str | None = Field(description="the session that computed the poses")
    source_version: int | None = Field(description="for an activation: the version it copies")
    cycle: int | None
    converged: bool | None
    accuracy: dict[str, float | None] | None = Field(description="error against the session's reference, when it had one")
    cameras: int
    active: bool


class Activate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    reason: str | None = Field(None, max_length=1000, description="why (kept in the history)")


class SensorOut(BaseModel):
    name: str
    online: bool | None = Field(description="liveliness token present (null: the sensor declares none)")
    messages: int
    accepted: int
    rejected: dict[str, int] = Field(description="rejected messages by reason")
    last_seen_ago: float | None = Field(description="wall seconds since its last message")
    last_stamp: float | None
    last_seq: int | None
    rate: float = Field(description="messages per second, recent")
    latency: dict[str, float] | None = Field(description="arrival − stamp, s (median, p95, max over the recent window)")
    clock_offset: float | None = Field(description="min(arrival − stamp) over the window: the sensor clock's lag behind ours plus the fastest transport delay")
    time_offset: dict[str, float | int | str | None] | None = Field(
        None, description="the running session's estimate of this sensor's clock offset from the data "
        "(clock.estimate; \"auto\", the default: once a sensor's stamps run apart from the others'): offset and std "
        "s relative to the median sensor (std: the larger of std_blocks, the jackknife over blocks of data time, and "
        "std_references, how far the offset moves with each camera that places the persons left out, measured at the "
        "end of a run, null before), applied s, blocks, drift_warnings, "
        "note (why its last update left the estimate as it was, null when it was updated)")
    keypoints: dict[str, float | int] | None = Field(
        None, description="the running session's preprocessing of its detections: torso_keypoints detected, "
        "below_confidence: the share of them under preprocess.min_confidence (dropped), confidence_scale: the "
        "factor its confidences are scaled by (preprocess.confidence_reference), outside_image: the share of all "
        "its detected joints outside the message's size (dropped), beyond_lens_model: the share where its lens "
        "model folds back (dropped)")
    warnings: list[str] = Field(default_factory=list, description="a clock set apart from the other sensors' by more than "
                                "the frameset std limit, messages arriving later than framesets wait, or most of its "
                                "torso keypoints below the confidence threshold, or many of its keypoints outside its images or where its "
                                "lens model folds back")


class Status(BaseModel):
    as_of: float = Field(description="wall time (s since the epoch) the status was made")
    site: str
    uptime: float
    clock: dict[str, Any] = Field(description="the pipeline's clock: mode (wall or data), speed, now")
    zenoh: dict[str, Any] = Field(description="mode, endpoints; routers and peers linked now; lost_since: wall time "
                                  "the links to the connect endpoints went (null: linked), losses; last_message_ago (s)")
    sensors: dict[str, SensorOut]
    messages: dict[str, Any] = Field(description="received, rejected by reason, ignored (no session)")
    framesets: dict[str, Any] | None = Field(description="accepted, rejected by reason")
    pipeline: dict[str, Any] | None = Field(description="the engine's counters")
    queues: dict[str, Any] = Field(description="ingest hand-off (length, capacity, dropped), hypotheses, writer")
    cycles: dict[str, Any] = Field(description="count and times (s) from problem to applied, and of the solve")
    frameset_delay: dict[str, float] | None = Field(description="s from a frameset's instant to its emission on the service clock (last, mean, p95, max)")
    loop_lag: dict[str, float | None] = Field(description="s the event loop woke up late (max since start, p99 recent)")
    loop_work: dict[str, dict[str, float]] = Field(description="s the synchronous steps on the loop take (count, mean, max)")
    storage: dict[str, Any]
    session: dict[str, Any] | None


class Health(BaseModel):
    ok: bool
    session: str | None
    state: str | None
