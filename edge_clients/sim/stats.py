"""What a simulated run contained, as figures and a table."""

from __future__ import annotations

from dataclasses import asdict, dataclass


from backend.cameras import natural_key

from .sensors import GROUP_NAMES


@dataclass(frozen=True)
class SimStats:
    """Figures of one run.

    messages: sensor → messages sent; with_person: sensor → share of its messages with
    at least one real person; rates: sensor → capture rate Hz; visible_joints: mean
    joints reported (confidence > 0) per detected person, confident_joints: with
    confidence >= 0.6; cameras_seeing: k → share of person-time (0.2 s bins) in which
    exactly k cameras detected that person (k = 0..S); noise_rms: joint group → RMS
    pixel error injected on correctly placed visible joints; counts of detections, false
    detections, missed persons (visible enough but not detected), left/right swaps,
    snapped joints, hidden joints guessed, duplicate detections (``duplicate_prob``).
    """

    duration: float
    persons: int
    heights: tuple[float, ...]
    messages: dict[str, int]
    with_person: dict[str, float]
    rates: dict[str, float]
    detections: int
    false_detections: int
    missed: int
    swaps: int
    snaps: int
    guessed_joints: int
    visible_joints: float
    confident_joints: float
    cameras_seeing: dict[int, float]
    noise_rms: dict[str, float]
    clock_offset_ms: dict[str, float]
    delay_ms: dict[str, float]
    duplicates: int = 0

    @property
    def total_messages(self) -> int:
        return sum(self.messages.values())

    def seen_by_at_least(self, k: int) -> float:
        """Share of person-time in which >= k cameras detected the person."""
        return float(sum(v for c, v in self.cameras_seeing.items() if c >= k))

    def mean_cameras(self) -> float:
        return float(sum(c * v for c, v in self.cameras_seeing.items()))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["cameras_seeing"] = {str(k): v for k, v in self.cameras_seeing.items()}
        return d

    def table(self) -> str:
        names = sorted(self.messages, key=natural_key)
        lines = [
            f"simulated {self.duration:.1f} s, {self.persons} persons "
            f"(heights {', '.join(f'{h:.2f}' for h in self.heights)} m), {len(names)} sensors, "
            f"{self.total_messages} messages",
            "",
            f"{'sensor':<10} {'rate Hz':>8} {'messages':>9} {'with person':>12} {'clock ms':>9} {'delay ms':>9}",
        ]
        for n in names:
            lines.append(f"{n:<10} {self.rates[n]:>8.1f} {self.messages[n]:>9d} {100 * self.with_person[n]:>11.1f}% "
                         f"{self.clock_offset_ms[n]:>+9.2f} {self.delay_ms[n]:>9.1f}")
        allm = self.total_messages
        share = (sum(self.with_person[n] * self.messages[n] for n in names) / allm) if allm else 0.0
        lines.append(f"{'all':<10} {'':>8} {allm:>9d} {100 * share:>11.1f}%")
        lines.append("")
        lines.append(f"detections of persons: {self.detections}; mean joints per detection: "
                     f"{self.visible_joints:.1f} reported, {self.confident_joints:.1f} with confidence >= 0.6")
        lines.append(f"false detections: {self.false_detections}; missed persons: {self.missed}; "
                     f"left/right swaps: {self.swaps}; snapped joints: {self.snaps}; "
                     f"hidden joints guessed: {self.guessed_joints}"
                     + (f"; duplicate detections: {self.duplicates}" if self.duplicates else ""))
        lines.append("")
        lines.append("cameras detecting a person at a time (share of person-time, 0.2 s bins):")
        ks = sorted(self.cameras_seeing)
        buckets = [(0, 0), (1, 1), (2, 2), (3, 3), (4, 5), (6, 8), (9, 10**6)]
        cells = []
        for lo, hi in buckets:
            v = sum(self.cameras_seeing[k] for k in ks if lo <= k <= hi)
            label = str(lo) if lo == hi else (f"{lo}-{hi}" if hi < 10**6 else f">={lo}")
            cells.append(f"{label}: {100 * v:.1f}%")
        lines.append("  " + "  ".join(cells))
        lines.append(f"  mean {self.mean_cameras():.2f} cameras; seen by >= 2 cameras {100 * self.seen_by_at_least(2):.1f}% of the time")
        lines.append("")
        lines.append("injected pixel noise (RMS over x and y, px): " + ", ".join(
            f"{g} {self.noise_rms.get(g, float('nan')):.2f}" for g in GROUP_NAMES))
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.table()


class StatsCollector:
    """Counts messages while a run is written (the detector counts the rest)."""

    def __init__(self, names: tuple[str, ...]):
        self.messages = {n: 0 for n in names}
        self.with_person = {n: 0 for n in names}
        self.false = 0

    def add(self, sensor: str, dets) -> None:
        self.messages[sensor] += 1
        real = sum(1 for d in dets if d.person >= 0)
        if real:
            self.with_person[sensor] += 1
        self.false += len(dets) - real
