"""Operator tools of the `extrcal` command: `export` and `report`."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from .cli import fail


def register(app: typer.Typer) -> None:
    app.command("export")(export_cmd)
    app.command("report")(report_cmd)


def export_cmd(
    result: Annotated[Path, typer.Argument(help="extrinsics YAML (a result, a reference, an initial estimate)",
                                           exists=True, dir_okay=False)],
    fmt: Annotated[str, typer.Option("--format", "-f",
                                     help="ais, json, opencv, pose2sim, kalibr or colmap")] = "ais",
    intrinsics: Annotated[Optional[Path], typer.Option(
        help="intrinsics YAML; needed by opencv, pose2sim, kalibr and colmap",
        exists=True, dir_okay=False)] = None,
    out: Annotated[Optional[Path], typer.Option(
        help="output file (default: standard output). colmap: a .zip file, or a directory "
             "that gets cameras.txt, images.txt and points3D.txt")] = None,
) -> None:
    """Write a calibration in the format of another tool (OpenCV, Pose2Sim, kalibr, COLMAP...).

    Poses are converted to each tool's convention (most want world→camera); see
    backend/export.py for what each format holds and what it cannot hold."""
    from .cameras import CameraFileError, load_extrinsics, load_intrinsics, write_atomic
    from .export import FORMATS, ExportError, colmap_files, export, export_warnings

    if fmt not in FORMATS:
        raise fail(f"unknown format {fmt!r}; choose one of {', '.join(FORMATS)}")
    try:
        ext = load_extrinsics(result)
        intr = load_intrinsics(intrinsics) if intrinsics else {}
    except CameraFileError as e:
        raise fail(str(e))
    try:
        if fmt == "colmap" and out is not None and out.suffix.lower() != ".zip":
            files = colmap_files(ext, intr)
            body: str | bytes = b""
        else:
            body, _ = export(ext, intr, fmt)
    except ExportError as e:
        raise fail(str(e))
    for w in export_warnings(ext, intr, fmt):
        typer.secho(f"warning: {w}", err=True, fg=typer.colors.YELLOW)
    if out is None:
        if isinstance(body, bytes):
            raise fail(f"the {fmt} export is binary (a zip); give --out FILE.zip or --out DIR")
        typer.echo(body, nl=False)
        return
    if fmt == "colmap" and out.suffix.lower() != ".zip":
        if out.exists() and not out.is_dir():
            raise fail(f"{out} exists and is not a directory")
        for name, text in files.items():
            write_atomic(out / name, text)
        typer.echo(f"wrote {out}/{{{','.join(files)}}} ({len(ext)} cameras, COLMAP text model)", err=True)
        return
    write_atomic(out, body)
    typer.echo(f"wrote {out} ({len(ext)} cameras, {fmt})", err=True)


def report_cmd(
    session: Annotated[Path, typer.Argument(
        help="session directory written by the service, or a history JSON Lines file of "
             "`extrcal calibrate --history`", exists=True)],
    out: Annotated[Path, typer.Option(help="HTML file to write")] = Path("report.html"),
    intrinsics: Annotated[Optional[Path], typer.Option(
        help="intrinsics YAML, if the session directory has none", exists=True, dir_okay=False)] = None,
    initial: Annotated[Optional[Path], typer.Option(
        help="initial extrinsics YAML, if the session directory has none", exists=True, dir_okay=False)] = None,
    result: Annotated[Optional[Path], typer.Option(
        help="result extrinsics YAML, if the session directory has none", exists=True, dir_okay=False)] = None,
    reference: Annotated[Optional[Path], typer.Option(
        help="reference extrinsics YAML, to plot and to measure the errors against",
        exists=True, dir_okay=False)] = None,
    room: Annotated[Optional[Path], typer.Option(
        help="room.yaml with the floor plane (floor.normal_up, floor.e1) for the top view",
        exists=True, dir_okay=False)] = None,
    recording: Annotated[Optional[Path], typer.Option(
        help="keypoint recording of the session: compute per-camera and per-joint-group "
             "reprojection errors of the result on it", exists=True, dir_okay=False)] = None,
    title: Annotated[Optional[str], typer.Option(help="report title")] = None,
) -> None:
    """Write a self-contained HTML report of a calibration session: camera plot, convergence
    over cycles, per-camera and per-joint-group reprojection errors, accuracy vs reference."""
    from proto import RecordingError

    from .cameras import CameraFileError, write_atomic
    from .report import ReportError, load_session, render_html

    try:
        data = load_session(session, intrinsics=intrinsics, initial=initial, result=result,
                            reference=reference, room=room, recording=recording)
    except (ReportError, CameraFileError, RecordingError) as e:
        raise fail(str(e))
    for w in data.warnings:
        typer.secho(f"warning: {w}", err=True, fg=typer.colors.YELLOW)
    html = render_html(data, title=title)
    write_atomic(out, html)
    typer.echo(f"wrote {out} ({len(data.cycles)} cycles, {len(data.camera_names)} cameras)", err=True)
