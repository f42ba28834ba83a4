"""`extrcal calibrate`: the online pipeline on a recording, on virtual time."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer


def register(app: typer.Typer) -> None:
    app.command()(calibrate)


def calibrate(
    intrinsics: Annotated[Path, typer.Option(help="intrinsics YAML (FORMATS.md)")],
    initial: Annotated[Path, typer.Option(help="initial extrinsics estimate YAML; its world frame and scale are kept")],
    recording: Annotated[Path, typer.Option(help="keypoint recording: .jsonl, .jsonl.gz or .msgpack")],
    output: Annotated[Path, typer.Option(help="where to write the resulting extrinsics YAML (atomically)")],
    reference: Annotated[Optional[Path], typer.Option(help="reference extrinsics: report the error against it")] = None,
    config: Annotated[Optional[Path], typer.Option(help="TOML file with engine parameters (sections sync, preprocess, associate, select, optimize, refine)")] = None,
    set_: Annotated[Optional[list[str]], typer.Option("--set", help="override one parameter, e.g. --set select.scope=80 (repeatable)")] = None,
    seed: Annotated[int, typer.Option(help="seed of the hypothesis selection")] = 0,
    history: Annotated[Optional[Path], typer.Option(help="write one JSON line per cycle: poses, std, cycle time, error vs reference")] = None,
    skip_bad: Annotated[bool, typer.Option(help="skip malformed records (counted) instead of stopping at the first")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress line")] = False,
) -> None:
    """Calibrate offline: run the full online pipeline on a recording as fast as the CPU
    allows (an optimisation cycle every 0.5 s of data time, like the live service) and
    write the result with per-camera std. Cameras that never got enough observations keep
    their initial pose and are named as not calibrated."""
    import json
    import time

    from rich.console import Console

    from proto import ReadStats, RecordingError, read_recording

    from .cameras import CameraFileError, CameraSet, load_extrinsics, save_extrinsics
    from .cli import fail
    from .config import ConfigError, EngineConfig
    from .evaluate import evaluate
    from .pipeline import run_offline

    console = Console(stderr=True)
    try:
        cfg = EngineConfig.load(config, set_ or [])
        cams = CameraSet.load(intrinsics, initial)
        ref = {k: v.pose for k, v in load_extrinsics(reference).items()} if reference else None
    except (ConfigError, CameraFileError) as e:
        raise fail(str(e))
    if ref is not None:
        common = set(ref) & set(cams.names)
        if len(common) < 3:
            raise fail(f"the reference {reference} shares {len(common)} cameras with the calibration; "
                       "at least 3 cameras are needed to compare them")
    if not recording.is_file():
        raise fail(f"recording {recording} does not exist")

    stats = ReadStats()
    hist_f = open(history, "w") if history else None
    t_start = time.perf_counter()
    last_print = [0.0]
    first_stamp: list[float] = []

    def messages():
        for m in read_recording(recording, skip_bad=skip_bad, stats=stats):
            if not first_stamp:
                first_stamp.append(m.stamp)
            yield m

    def progress(state, report) -> None:
        err = None
        if ref is not None:
            try:
                err = evaluate(state.poses(), ref)
            except ValueError:
                err = None
        if hist_f is not None:
            rec = {
                "cycle": report.cycle,
                "data_time": state.data_time,
                "report": report.to_dict(),
                "cameras": [c.to_dict() for c in state.cameras],
            }
            if err is not None:
                rec["error"] = {"position": err.position.mean, "orientation": err.orientation.mean,
                                "shape_position": err.shape_position.mean,
                                "shape_orientation": err.shape_orientation.mean, "scale": err.scale}
            hist_f.write(json.dumps(rec) + "\n")
        now = time.perf_counter()
        if quiet or now - last_print[0] < 0.5:
            return
        last_print[0] = now
        t_data = (state.data_time or 0) - (first_stamp[0] if first_stamp else 0)
        n_conv = sum(c.converged for c in state.cameras)
        line = (f"data {t_data:7.1f} s | cycle {report.cycle:4d} | hyp {state.counters.hypotheses:6d} "
                f"| obs/cam {int(sum(c.observations for c in state.cameras) / len(state.cameras)):6d} "
                f"| converged {n_conv}/{len(state.cameras)} | solve {report.solve_seconds * 1000:4.0f} ms")
        if err is not None:
            line += f" | err {err.position.mean:.4f} m {err.orientation.mean:.3f}° (shape {err.shape_position.mean:.4f} m)"
        console.print(line, highlight=False)

    try:
        p = run_offline(cams, cfg, messages(), seed=seed, progress=progress)
    except RecordingError as e:
        raise fail(f"{e} (use --skip-bad to skip malformed records)")
    finally:
        if hist_f is not None:
            hist_f.close()
    state = p.state()
    wall = time.perf_counter() - t_start
    not_calibrated = [c.name for c in state.cameras if c.cycles == 0]
    extr = state.extrinsics({n: cams.extrinsics[n].resolution for n in cams.names})
    comment = (f"extrcal calibrate of {recording}: {state.cycle} cycles, "
               f"converged: {sum(c.converged for c in state.cameras)}/{len(state.cameras)}")
    if not_calibrated:
        comment += f"\nnot calibrated (kept initial pose): {', '.join(not_calibrated)}"
    extra = {n: {"calibrated": n not in not_calibrated} for n in cams.names}
    save_extrinsics(output, extr, comment=comment, extra=extra)

    span = (state.data_time or 0) - (first_stamp[0] if first_stamp else 0)
    c = state.counters
    console.print(
        f"{c.messages} messages ({stats.skipped} bad records skipped), {c.framesets} framesets "
        f"({sum(c.framesets_rejected.values())} rejected), {c.hypotheses} hypotheses, {state.cycle} cycles "
        f"({c.cycles_rejected} rejected) in {wall:.1f} s = {span / max(wall, 1e-9):.1f}x real time",
        highlight=False,
    )
    if not_calibrated:
        console.print(f"[yellow]not calibrated (too few observations, initial pose kept): {', '.join(not_calibrated)}[/]")
    if ref is not None:
        console.print(f"vs reference: {evaluate(state.poses(), ref).summary()}", highlight=False)
    typer.echo(f"wrote {output}")
