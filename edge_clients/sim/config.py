"""Every knob of the simulator, with defaults that look like the paper's lab."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields


@dataclass(frozen=True)
class SimConfig:
    """What is simulated and how badly the sensors behave.

    Run
      persons: number of people walking (>= 0).
      duration: seconds of true time to simulate; ``math.inf`` runs until the caller stops.
      seed: the one seed; the world derives from it, each sensor from (seed, sensor name).
      heights: body heights in m, one per person; None draws them from N(1.75, 0.07)
        clipped to [1.55, 2.0] (from the world's stream).
      start_time: true time of t = 0, seconds since the Unix epoch (the caller passes the
        wall clock for live use; the default keeps recordings reproducible).
      noise: False turns off every detector error: pixel noise, rounding, confidence
        jitter, gross errors, missed and false detections, noisy guesses of hidden joints.
        What remains is exact projection of the visible joints (image bounds, walls,
        other people and the face seen from behind still hide joints), confidence from
        the visibility model, and the timing model (clocks, rates, delays, drops).
      noise_scale: multiplies every pixel noise sigma.

    World
      world_rate: Hz at which the walkers and skeletons are computed; joints between two
        ticks are linearly interpolated (this interpolation *is* the ground truth).
      camera_height: m of the cameras above the floor, used only to find the floor when
        the scene has no room.yaml (see Scene).
      speed: (min, max) m/s cruising speed, drawn per person and per leg of the walk.
      step_freq: steps per second at 1.3 m/s (scales with the square root of speed).
      turn_rate: deg/s, the fastest a walker turns.
      pause_prob: chance to stop at a waypoint; pause: (min, max) s of a stop.
      bend_prob, reach_prob: chance that a stop includes bending down / reaching up.
      leave_prob: chance that a waypoint lies where fewer than 2 cameras see (people
        leave the views).
      min_separation: m, people never come closer (centre to centre); they slow down,
        swerve and wait for each other before that.
      coverage_range: m, a camera "covers" floor points whose torso is at most this far.

    Sensors (timing)
      rates: (min, max) Hz, each sensor's capture rate is drawn uniformly in it.
      sensor_rates: {sensor: Hz} overrides for some sensors.
      frame_jitter: s, std of a capture instant around its nominal time.
      stamp_jitter: s, std of a stamp's error about its frame's capture instant (normal,
        cut at 3 std; default 0): a sensor that stamps a frame when it gets it from the
        driver or when its detector is done with it, not when it was exposed. Its own
        random stream: every other draw stays as it was.
      drop_prob: chance that a frame is lost (its ``seq`` is skipped).
      stall_prob, stall: chance per frame that the sensor stalls for (min, max) s,
        losing every frame meanwhile (Wi-Fi hiccup, detector hang).
      clock_std: s, std of each sensor's constant NTP clock error.
      drift_std: std of each sensor's clock rate error (1e-6 = 1 ppm).
      delay: (min, max) s, each sensor's base network + processing delay.
      delay_jitter: s, mean of the extra per-message delay (gamma distributed).
      clock_offsets: {sensor: s} constant clock offsets that replace the drawn NTP error
        (a sensor whose NTP fails: stamp = capture + offset + drift x elapsed).
      clock_drifts: {sensor: s/s} clock rate errors that replace the drawn drift.

    Scenarios
      bumps: ((time_s, sensor, translation_m, rotation_deg), ...): from true time
        ``time_s`` (relative to the start) on, the sensor's camera is moved by
        ``translation_m`` in a random direction and turned by ``rotation_deg`` about a
        random axis through its optical centre (both drawn from (seed, "bump", sensor,
        index)); several bumps of one sensor add up. The truth records the new poses.

    Detector
      sigma_torso, sigma_head, sigma_limb, sigma_extremity: px pixel noise std at
        848x480 for shoulders/hips, nose/eyes/ears, elbows/knees, wrists/ankles, per
        axis, for a person 150 px tall. Scaled with the image size (square root of the
        pixel count) and with the square root of the person's size in the image (clipped
        to x0.6..x1.6); half of the variance is correlated over time (``noise_tau``).
      noise_tau: s, correlation time of the correlated part of the pixel noise.
      swap_prob: chance that a detection has its left and right swapped (whole body or
        one limb pair; four times as likely when the person is seen from behind).
      snap_prob: chance, per pair of overlapping people in an image, that a joint of one
        is reported on the other.
      miss_prob: chance that a clearly visible person is not detected (more when small,
        truncated or occluded); miss_burst: the chance right after a miss (misses come in
        bursts of a few frames).
      min_person_px: px, persons whose visible part is shorter than this are mostly missed.
      false_rate: mean number of random false detections per frame.
      ghost_prob, ghost_rate: chance that a sensor has a persistent false detection (a
        poster, a coat) and how often per frame it fires.
      duplicate_prob: chance that a detected person is detected twice in a frame (a
        top-down detector whose non-maximum suppression let two boxes on one person
        through): the second skeleton lies on the first, a little off (1.5 % of the
        person's height per joint), with fewer joints and a lower score; the truth gives
        it the same person and ``FLAG_DUPLICATE``. Its own random stream: 0 (the default)
        and any other value leave every other detection as it was.
      hidden_drop: chance that a hidden joint (occluded, face from behind) is dropped;
        otherwise it is guessed with large noise and low confidence.
      pixel_decimals: pixel coordinates and confidences are rounded to this many decimals
        (None: full float64); ignored when ``noise`` is False.
      surface_offset: m; a detector's keypoints are not joint centres but where annotators
        put them on the body's outline: seen from the front or back, a shoulder's keypoint
        lies this far out from the joint, seen from the side on it (the lateral offset
        perpendicular to the camera's ray; hips 1.25x, elbows and knees 0.5x, wrists and
        ankles 0.25x, the head 0). Triangulated from two views, such keypoints disagree by
        up to this much: a systematic, view-dependent error that no noise model states.
        0 (the default) puts keypoints on the joints. Off when ``noise`` is False.
      intrinsics_error: the real lenses differ from the calibration files the backend
        gets: relative std of the focal length (the principal point moves by this times
        half the image width, in px). Off when ``noise`` is False; the truth keeps the
        lenses used (``lens_fx`` ...).
    """

    persons: int = 2
    duration: float = 180.0
    seed: int = 0
    heights: tuple[float, ...] | None = None
    start_time: float = 1.7e9
    noise: bool = True
    noise_scale: float = 1.0
    # world
    world_rate: float = 100.0
    camera_height: float = 2.6
    speed: tuple[float, float] = (1.0, 1.5)
    step_freq: float = 1.8
    turn_rate: float = 120.0
    pause_prob: float = 0.5
    pause: tuple[float, float] = (2.0, 6.0)
    bend_prob: float = 0.25
    reach_prob: float = 0.2
    leave_prob: float = 0.1
    min_separation: float = 0.5
    coverage_range: float = 12.0
    # sensors: timing
    rates: tuple[float, float] = (10.0, 30.0)
    sensor_rates: tuple[tuple[str, float], ...] = ()
    frame_jitter: float = 0.001
    stamp_jitter: float = 0.0
    drop_prob: float = 0.01
    stall_prob: float = 0.0003
    stall: tuple[float, float] = (0.2, 1.5)
    clock_std: float = 0.003
    drift_std: float = 2e-6
    delay: tuple[float, float] = (0.02, 0.08)
    delay_jitter: float = 0.008
    # detector
    sigma_torso: float = 2.0
    sigma_head: float = 2.3
    sigma_limb: float = 3.3
    sigma_extremity: float = 4.8
    noise_tau: float = 0.3
    swap_prob: float = 0.005
    snap_prob: float = 0.1
    miss_prob: float = 0.03
    miss_burst: float = 0.4
    min_person_px: float = 40.0
    false_rate: float = 0.02
    ghost_prob: float = 0.3
    ghost_rate: float = 0.05
    duplicate_prob: float = 0.0
    hidden_drop: float = 0.5
    pixel_decimals: int | None = 3
    intrinsics_error: float = 0.002
    surface_offset: float = 0.0
    # scenarios
    clock_offsets: tuple[tuple[str, float], ...] = ()
    clock_drifts: tuple[tuple[str, float], ...] = ()
    bumps: tuple[tuple[float, str, float, float], ...] = ()

    def __post_init__(self) -> None:
        def bad(name: str, why: str) -> None:
            raise ValueError(f"SimConfig.{name}: {why}")

        if isinstance(self.sensor_rates, dict):  # accept a mapping, store it hashable
            object.__setattr__(self, "sensor_rates", tuple(sorted(self.sensor_rates.items())))
        for name in ("clock_offsets", "clock_drifts"):
            v = getattr(self, name)
            items = v.items() if isinstance(v, dict) else v
            try:
                norm = tuple(sorted((str(k), float(x)) for k, x in items))
            except (TypeError, ValueError):
                bad(name, f"expected {{sensor: seconds}}, got {v!r}")
            if any(not math.isfinite(x) for _, x in norm):
                bad(name, f"values must be finite, got {dict(norm)}")
            object.__setattr__(self, name, norm)
        bumps = []
        for b in self.bumps:
            try:
                t, sensor, dt, dr = b
                b = (float(t), str(sensor), float(dt), float(dr))
            except (TypeError, ValueError):
                bad("bumps", f"expected (time_s, sensor, translation_m, rotation_deg), got {b!r}")
            if not (math.isfinite(b[0]) and b[0] >= 0 and math.isfinite(b[2]) and b[2] >= 0
                    and math.isfinite(b[3]) and 0 <= b[3] <= 180):
                bad("bumps", f"{b}: time >= 0, translation >= 0 m and rotation in [0, 180] deg expected")
            bumps.append(b)
        object.__setattr__(self, "bumps", tuple(sorted(bumps, key=lambda b: (b[0], b[1]))))
        if self.persons < 0:
            bad("persons", f"must be >= 0, got {self.persons}")
        if not (self.duration > 0):
            bad("duration", f"must be > 0 (inf allowed), got {self.duration}")
        if self.heights is not None:
            object.__setattr__(self, "heights", tuple(float(h) for h in self.heights))
            if len(self.heights) != self.persons:
                bad("heights", f"{len(self.heights)} heights for {self.persons} persons")
            if any(not (1.0 <= h <= 2.3) for h in self.heights):
                bad("heights", f"expected body heights in m between 1.0 and 2.3, got {self.heights}")
        if not math.isfinite(self.start_time) or self.start_time <= 0:
            bad("start_time", f"must be seconds since the Unix epoch, got {self.start_time}")
        if self.world_rate < 20:
            bad("world_rate", f"must be >= 20 Hz, got {self.world_rate}")
        for name in ("speed", "pause", "rates", "stall", "delay"):
            lo, hi = getattr(self, name)
            if not (0 <= lo <= hi):
                bad(name, f"expected (min, max) with 0 <= min <= max, got {(lo, hi)}")
        if self.rates[0] <= 0:
            bad("rates", "rates must be > 0 Hz")
        for s, r in self.sensor_rates:
            if not r > 0:
                bad("sensor_rates", f"{s}: rate must be > 0 Hz, got {r}")
        for name in ("pause_prob", "bend_prob", "reach_prob", "leave_prob", "drop_prob",
                     "stall_prob", "swap_prob", "snap_prob", "miss_prob", "miss_burst", "ghost_prob",
                     "ghost_rate", "duplicate_prob", "hidden_drop"):
            p = getattr(self, name)
            if not 0 <= p <= 1:
                bad(name, f"a probability in [0, 1], got {p}")
        for name in ("noise_scale", "clock_std", "drift_std", "delay_jitter", "frame_jitter", "stamp_jitter",
                     "false_rate", "sigma_torso", "sigma_head", "sigma_limb", "sigma_extremity",
                     "intrinsics_error", "surface_offset"):
            if getattr(self, name) < 0:
                bad(name, f"must be >= 0, got {getattr(self, name)}")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["duration"] = None if math.isinf(self.duration) else self.duration
        return d

    @staticmethod
    def field_names() -> tuple[str, ...]:
        return tuple(f.name for f in fields(SimConfig))
