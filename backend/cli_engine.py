"""`extrcal calibrate`: the online pipeline on a recording, on virtual time."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer


def register(app: typer.Typer) -> None:
    app.command()(calibrate)


def calibrate(
    intrinsics: Annotated[Path, typer.Option(help="intrinsics YAML (FORMATS.md)")],
    recording: Annotated[Path, typer.Option(help="keypoint recording: .jsonl, .jsonl.gz or .msgpack")],
    output: Annotated[Path, typer.Option(help="where to write the resulting extrinsics YAML (atomically)")],
    initial: Annotated[Optional[Path], typer.Option(help="initial extrinsics estimate YAML; its world frame and scale are kept "
                                                    "(when the data disagree with it, the run starts from the data's shape: "
                                                    "bootstrap.with_initial). Without it the cameras are found from the people "
                                                    "alone (docs/bootstrap.md)")] = None,
    distrust_initial: Annotated[bool, typer.Option("--distrust-initial", help="ignore the initial estimate's poses: bootstrap as without one")] = False,
    person_height: Annotated[Optional[str], typer.Option(help="known height(s) of the walkers in m, e.g. 1.85 or 1.96,1.70: "
                                                         "metric scale from them (else from a population prior); with "
                                                         "--initial, the result's scale is checked against them and "
                                                         "corrected (bootstrap.initial_scale)")] = None,
    reference: Annotated[Optional[Path], typer.Option(help="reference extrinsics: report the error against it")] = None,
    config: Annotated[Optional[Path], typer.Option(help="TOML file with engine parameters (sections sync, preprocess, associate, select, optimize, refine, bootstrap)")] = None,
    set_: Annotated[Optional[list[str]], typer.Option("--set", help="override one parameter, e.g. --set select.scope=80 (repeatable)")] = None,
    seed: Annotated[int, typer.Option(help="seed of the hypothesis selection")] = 0,
    history: Annotated[Optional[Path], typer.Option(help="write one JSON line per cycle: poses, std, cycle time, error vs reference")] = None,
    skip_bad: Annotated[bool, typer.Option(help="skip malformed records (counted) instead of stopping at the first")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress line")] = False,
) -> None:
    """Calibrate offline: run the full online pipeline on a recording as fast as the CPU
    allows (an optimisation cycle every 0.5 s of data time, like the live service) and
    write the result with per-camera std. Cameras that never got enough observations keep
    their initial pose and are named as not calibrated.

    Without --initial (or with --distrust-initial) the first bootstrap.max_seconds of the
    recording find the cameras first (relative poses from single persons seen by camera
    pairs, a bundle adjustment, metric scale from the people, the floor as the world
    frame); the online pipeline then runs on the whole recording from that estimate."""
    import json
    import time

    from rich.console import Console

    from proto import ReadStats, RecordingError, read_recording

    from .cameras import CameraFileError, CameraSet, load_extrinsics, load_intrinsics, save_extrinsics, save_intrinsics
    from .cli import fail
    from .config import ConfigError, EngineConfig
    from .evaluate import MIN_CAMERAS, evaluate
    from .pipeline import run_offline

    console = Console(stderr=True)
    heights: list[float] = []
    if person_height:
        try:
            heights = [float(x) for x in person_height.split(",") if x.strip()]
        except ValueError:
            raise fail(f"--person-height: expected heights in m separated by commas, got {person_height!r}")
        if not heights or any(not 0.5 <= h <= 2.8 for h in heights):
            raise fail(f"--person-height: heights must lie in 0.5-2.8 m, got {person_height!r}")
    try:
        cfg = EngineConfig.load(config, set_ or [])
        intr = load_intrinsics(intrinsics)
        if initial is not None:
            cams = CameraSet.combine(intr, load_extrinsics(initial), str(intrinsics), str(initial))
        ref = {k: v.pose for k, v in load_extrinsics(reference).items()} if reference else None
        # px parameters in the keypoints' pixels: the initial estimate names the messages' size
        # (CameraSet.combine takes the intrinsics' where it names none)
        cfg = cfg.for_images(cams.sizes if initial is not None else [i.resolution for i in intr.values()])
    except (ConfigError, CameraFileError) as e:
        raise fail(str(e))
    if not recording.is_file():
        raise fail(f"recording {recording} does not exist")
    boot = None
    if initial is None or distrust_initial:
        from .bootstrap import BootstrapError, bootstrap_messages, camera_set, handover, mistimed_summary
        from .cameras import natural_key

        names = tuple(sorted(intr, key=natural_key))
        if not quiet:
            console.print(f"no initial estimate{' (distrusted)' if initial is not None else ''}: bootstrapping from "
                          f"the first {cfg.bootstrap.max_seconds:g} s of data" if cfg.bootstrap.max_seconds
                          else "no initial estimate: bootstrapping from the whole recording", highlight=False)
        say = (lambda m: None) if quiet else (lambda m: console.print(f"bootstrap: {m}", highlight=False))
        try:
            boot = bootstrap_messages(intr, cfg, read_recording(recording, skip_bad=skip_bad), heights=heights,
                                      seed=seed, progress=say)
        except RecordingError as e:
            raise fail(f"{e} (use --skip-bad to skip malformed records)")
        except BootstrapError as e:
            more = (f" in the first {cfg.bootstrap.max_seconds:g} s of data (`--set bootstrap.max_seconds=0` "
                    f"bootstraps on the whole recording)") if cfg.bootstrap.max_seconds else ""
            raise fail(f"bootstrap failed: {e}{more}")
        cams = camera_set(intr, boot)
        cfg = handover(cfg, boot)
        lost = [n for c, n in enumerate(names) if not boot.located[c]]
        if not quiet:
            console.print(f"bootstrap: {int(boot.located.sum())}/{len(names)} cameras placed from "
                          f"{boot.data_seconds:.0f} s of data in {boot.seconds:.1f} s"
                          + (f"; not placed: {', '.join(lost)}" if lost else ""), highlight=False)
            if ref is not None and boot.located.sum() >= 3:
                console.print(f"bootstrap vs reference: {evaluate(boot.poses(), ref).summary()}", highlight=False)
    rec, start, note = None, None, ""
    if boot is None and cfg.bootstrap.with_initial != "never":
        # the data's shape aligned onto the initial estimate (backend/reconcile.py)
        from .reconcile import bootstrap_start

        if not quiet:
            console.print(f"bootstrap.with_initial = {cfg.bootstrap.with_initial}: comparing the initial estimate "
                          f"with the data's shape (bootstrap of the first {cfg.bootstrap.max_seconds:g} s)",
                          highlight=False)
        say = (lambda m: None) if quiet else (lambda m: console.print(f"bootstrap: {m}", highlight=False))
        try:
            rec, _, note = bootstrap_start(cams, intr, cfg, read_recording(recording, skip_bad=skip_bad), seed=seed,
                                           progress=say)
        except RecordingError as e:
            raise fail(f"{e} (use --skip-bad to skip malformed records)")
        if rec is not None:
            cfg, cams, start = rec.applied(cfg, cams)
        if not quiet:
            console.print(note, highlight=False)
            if rec is not None and rec.used:
                console.print(f"the online pipeline starts from the data's shape in the initial estimate's frame and "
                              f"scale; the initial estimate's std: {cfg.refine.initial_std_translation:.3f} m / "
                              f"{cfg.refine.initial_std_rotation:.2f}°", highlight=False)
    if ref is not None:
        common = set(ref) & set(cams.names)
        if len(common) < MIN_CAMERAS:
            raise fail(f"the reference {reference} shares {len(common)} cameras with the calibration; "
                       f"at least {MIN_CAMERAS} cameras are needed to compare them")

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

    joining = None
    if boot is not None and cfg.bootstrap.late and not boot.located.all():
        # the cameras it did not place: archived beside the pipeline, resected at the end (backend/late_join.py)
        from .late_join import JoiningPipeline

        joining = JoiningPipeline(cams, cfg, intrinsics=intr, names=boot.names, seed=seed)
    try:
        p = run_offline(cams, cfg, messages(), seed=seed, progress=progress,
                        start=start, pipeline=joining,
                        scale_heights=heights if boot is None else None,
                        data_shape=rec.data_shape() if rec is not None else None)
    except RecordingError as e:
        raise fail(f"{e} (use --skip-bad to skip malformed records)")
    finally:
        if hist_f is not None:
            hist_f.close()
    state = p.state()
    wall = time.perf_counter() - t_start
    late_lines: list[str] = []
    if joining is not None:
        from .late_join import late_comment

        joining = p  # the pipeline the run ended with: cameras may have joined it while it ran
        late_lines = late_comment(joining)
        cams = joining.joined.cameras if joining.joined is not None else joining.cameras
    started = {n for n, u in zip(rec.names, rec.from_bootstrap) if u} if rec is not None else set()
    not_calibrated = [c.name for c in state.cameras if c.cycles == 0 and c.name not in started]
    only_bootstrap = [c.name for c in state.cameras if c.cycles == 0 and c.name in started]
    extr = state.extrinsics({n: cams.extrinsics[n].resolution for n in cams.names})
    check = p.scale_check  # the initial estimate's scale against the people's (backend/scale_check.py)
    comment = (f"extrcal calibrate of {recording}: {state.cycle} cycles, "
               f"converged: {sum(c.converged for c in state.cameras)}/{len(state.cameras)}")
    far = p.far_from_start()
    far_line = ("far beyond the stated std of where they started (check their initial pose, or their data): "
                + ", ".join(f"{n} {m:.2f} m / {d:.1f}° (χ² {x:.0f})" for n, m, d, x in far)) if far else ""
    if not_calibrated:
        comment += f"\nnot calibrated (kept initial pose): {', '.join(not_calibrated)}"
    if far_line:
        comment += f"\n{far_line}"
    if p.retimed:  # offsets found during the run: the final batch had the views from before, too
        comment += ("\narchived views timed again with the final clock offsets: "
                    + ", ".join(f"{n} {k}" for n, k in p.retimed.items()))
    if only_bootstrap:
        comment += f"\nnot calibrated online (kept the bootstrap's pose): {', '.join(only_bootstrap)}"
    if p.last_report is not None and p.last_report.phantoms:
        comment += (f"\nfinal batch adjustment: {p.last_report.phantoms} hypotheses dropped as far larger than "
                    "anyone seen (two people's views, optimize.max_size_ratio)")
    if p.last_report is not None and p.last_report.floor_points:
        comment += (f"\nfinal batch adjustment: {p.last_report.floor_points} lower ankles held to the floor's plane "
                    f"(their spread about it {p.last_report.floor_spread:.3f} m; optimize.floor)")
    if p.split_check is not None:
        comment += f"\n{p.split_check.summary()}"
    std_note = p.std_note()
    if std_note is not None:
        comment += f"\n{std_note}"
    lens_file = Path(f"{output}.intrinsics.yaml")  # the lenses found, next to the result
    if p.lenses is not None:
        comment += f"\n{p.lenses.summary()}; the lenses: {lens_file}"
    if rec is not None:
        comment += f"\n{rec.summary()}"
        if p.final_batch_start == "anchored":
            comment += ("\nfinal batch adjustment: the online estimate ended apart from the data's shape; the one "
                        "held to the data's shape explained as much of the data within its hold, and was kept")
        elif p.final_batch_start == "data":
            comment += ("\nfinal batch adjustment: the one started from the data's shape explained the data better "
                        "than the one from the online estimate, and was kept")
        elif p.final_batch_start == "estimate":
            comment += ("\nfinal batch adjustment: also started from the data's shape (the online estimate ended "
                        "apart from it); the one from the online estimate explained the data better, and was kept")
    elif note:  # the check was not possible: say so, the result is the paper's way
        comment += f"\n{note}"
    scale = boot.scale if boot is not None else (check.people if check is not None else None)
    if boot is not None:
        comment += f"\nno initial estimate: {boot.frame}"
        if boot.mistimed:
            comment += f"\n{mistimed_summary(boot.mistimed)}"
        if p.levelled is not None:
            comment += f"\n{p.levelled.summary()}"
        comment += "".join(f"\n{ln}" for ln in late_lines)
        if p.final_batch_start is not None:
            comment += (f"\nfinal batch adjustment: kept the one started from the "
                        f"{'bootstrap' if p.final_batch_start == 'start' else 'online estimate'}")
        if scale is not None:
            comment += f"\nmetric scale from people: {scale.summary()}"
    elif check is not None:
        comment += f"\n{check.summary()}"
    extra = {n: {"calibrated": n not in not_calibrated and n not in only_bootstrap} for n in cams.names}
    save_extrinsics(output, extr, comment=comment, extra=extra)
    if p.lenses is not None:
        save_intrinsics(lens_file, p.lenses.intrinsics(cams.intrinsics))
    else:  # an earlier run's would read as this one's
        lens_file.unlink(missing_ok=True)
    if boot is not None:
        from .cameras import write_atomic

        meta = {**boot.to_dict(), "online": {"initial_std_translation": cfg.refine.initial_std_translation,
                                             "initial_std_rotation": cfg.refine.initial_std_rotation}}
        if joining is not None:
            meta["placed_later"] = [j.to_dict() for j in joining.late]
            meta["late_resections"] = list(joining.late_notes)
        write_atomic(Path(f"{output}.bootstrap.json"), json.dumps(meta, indent=1) + "\n")

    span = (state.data_time or 0) - (first_stamp[0] if first_stamp else 0)
    c = state.counters
    why = ", ".join(f"{k} {v}" for k, v in sorted(c.framesets_rejected.items(), key=lambda kv: -kv[1]) if v)
    console.print(
        f"{c.messages} messages ({stats.skipped} bad records skipped), {c.framesets} framesets "
        f"({sum(c.framesets_rejected.values())} rejected{': ' + why if why else ''}), {c.hypotheses} hypotheses, "
        f"{state.cycle} cycles "
        f"({c.cycles_rejected} rejected) in {wall:.1f} s = {span / max(wall, 1e-9):.1f}x real time",
        highlight=False,
    )
    if c.rejected:
        def by_sensor(reason: str) -> str:
            top = p.sync.rejected_sensors[reason].most_common() if reason in p.sync.rejected_sensors else []
            more = f", {len(top) - 5} more" if len(top) > 5 else ""
            return f" ({', '.join(f'{n} {k}' for n, k in top[:5])}{more})" if top else ""

        console.print("[yellow]messages rejected: " + ", ".join(
            f"{k} {v}{by_sensor(k)}" for k, v in sorted(c.rejected.items(), key=lambda kv: -kv[1]))
            + (f"; unknown sensors are ids not in {intrinsics}" if "unknown_sensor" in c.rejected else "") + "[/]",
            highlight=False)
    for ln in late_lines:
        console.print(ln, highlight=False)
    if not_calibrated:
        console.print(f"[yellow]not calibrated (too few observations, initial pose kept): {', '.join(not_calibrated)}[/]")
    if far_line:
        console.print(f"[yellow]{far_line}[/]", highlight=False)
    for name, rep in p.preprocess.confidence_report().items():
        if rep["warning"]:
            console.print(f"[yellow]{name}: {rep['warning']}[/]", highlight=False)
    if p.levelled is not None:
        console.print(p.levelled.summary(), highlight=False)
    if p.lenses is not None:
        console.print(f"{p.lenses.summary()}; written: {lens_file}", highlight=False)
    if p.split_check is not None:
        color = "yellow" if p.split_check.widened else "default"
        console.print(f"[{color}]{p.split_check.summary()}[/]", highlight=False)
    if scale is not None:
        if boot is not None:
            console.print(f"metric {scale.summary()}", highlight=False)
        elif check is not None:
            console.print(f"{check.summary()} ({len(scale.heights)} persons of "
                          f"{', '.join(f'{h:.2f}' for h in scale.heights)} m)", highlight=False)
    if ref is not None:
        console.print(f"vs reference: {evaluate(state.poses(), ref).summary()}", highlight=False)
    typer.echo(f"wrote {output}")
