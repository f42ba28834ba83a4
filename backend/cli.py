"""The `extrcal` command.

Each subcommand imports what it needs when it runs, so that an edge sensor with the
base install (no GTSAM, FastAPI or OpenCV) can use the sensor, replay and record
commands. Subcommands of other areas register themselves from their own modules.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

app = typer.Typer(
    name="extrcal",
    help=(
        "Online, marker-free extrinsic calibration of a camera network from 2D person "
        "keypoints.\n\nQuick start: `extrcal demo` runs simulated sensors, the service and a "
        "calibration session on this machine. Offline: `extrcal simulate`, `extrcal perturb`, "
        "`extrcal calibrate`, `extrcal evaluate`."
    ),
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def fail(message: str, code: int = 2) -> typer.Exit:
    """Print one clear error line and return the Exit to raise."""
    typer.secho(f"error: {message}", err=True, fg=typer.colors.RED)
    return typer.Exit(code)


ExistingFile = Annotated[Path, typer.Option(exists=True, dir_okay=False, readable=True)]


@app.command()
def perturb(
    reference: Annotated[Path, typer.Option(help="extrinsics YAML to perturb", exists=True, dir_okay=False)],
    out: Annotated[Path, typer.Option(help="where to write the perturbed extrinsics YAML")],
    translation: Annotated[float, typer.Option(help="m each camera is moved (random direction)")] = 0.25,
    rotation: Annotated[float, typer.Option(help="deg each camera is rotated (random axis)")] = 10.0,
    seed: int = 0,
    keep_first: Annotated[bool, typer.Option(help="leave the first camera untouched (the paper's protocol)")] = True,
) -> None:
    """Make an initial estimate: every camera but the first moved exactly TRANSLATION m in a
    random direction and rotated exactly ROTATION degrees about a random axis."""
    from .cameras import CameraFileError, load_extrinsics, save_extrinsics
    from .perturb import perturb_extrinsics

    try:
        ref = load_extrinsics(reference)
    except CameraFileError as e:
        raise fail(str(e))
    out_cams = perturb_extrinsics(ref, translation, rotation, seed=seed, keep_first=keep_first)
    save_extrinsics(out, out_cams, comment=f"extrcal perturb --translation {translation} --rotation {rotation} --seed {seed} of {reference}")
    typer.echo(f"wrote {out} ({len(out_cams)} cameras, {translation} m / {rotation} deg)")


@app.command()
def evaluate(
    result: Annotated[Path, typer.Option(help="extrinsics YAML to judge", exists=True, dir_okay=False)],
    reference: Annotated[Path, typer.Option(help="reference extrinsics YAML", exists=True, dir_okay=False)],
    json_out: Annotated[bool, typer.Option("--json", help="print the figures as JSON")] = False,
) -> None:
    """Accuracy of a calibration against a reference: rigid (the paper's) and shape
    (similarity) position and orientation errors, scale factor, per camera."""
    import json

    from .cameras import CameraFileError, load_extrinsics
    from .evaluate import evaluate as run

    try:
        res = {k: v.pose for k, v in load_extrinsics(result).items()}
        ref = {k: v.pose for k, v in load_extrinsics(reference).items()}
        acc = run(res, ref)
    except (CameraFileError, ValueError) as e:
        raise fail(str(e))
    if json_out:
        typer.echo(json.dumps(acc.to_dict(), indent=2))
        return
    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"{result} vs {reference}")
    for col in ("camera", "position m", "orientation °", "shape m", "shape °"):
        t.add_column(col, justify="right")
    for name, (p, o, sp, so) in acc.per_camera.items():
        t.add_row(name, f"{p:.4f}", f"{o:.3f}", f"{sp:.4f}", f"{so:.3f}")
    Console().print(t)
    typer.echo(acc.summary())


def main() -> None:
    _register_all()
    app()


def _register_all() -> None:
    """Commands of other areas live next to their code; each module adds its own."""
    import importlib

    for mod in ("edge_clients.cli_simulate", "backend.cli_engine", "backend.cli_service",
                "edge_clients.cli", "backend.cli_tools"):
        try:
            m = importlib.import_module(mod)
        except ModuleNotFoundError as e:
            if e.name == mod:
                continue  # that area is not built yet
            raise
        m.register(app)


if __name__ == "__main__":
    main()
