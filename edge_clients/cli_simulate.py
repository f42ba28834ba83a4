"""`extrcal simulate`: a recording of people walking through a camera network, with
its ground truth, from the realistic simulator (edge_clients/sim)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

LAB = Path(__file__).resolve().parent / "data" / "ais_lab20"


def _floats(text: str, what: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise typer.BadParameter(f"{what}: expected comma-separated numbers, got {text!r}") from None


def _per_sensor(text: str, what: str) -> dict[str, float]:
    """``cam_2:-0.2,cam_5:0.1`` -> {sensor: number} (clock_offsets, clock_drifts, sensor_rates)."""
    out = {}
    for item in (x.strip() for x in text.split(",") if x.strip()):
        name, sep, value = item.rpartition(":")
        try:
            if not sep or not name:
                raise ValueError
            out[name.strip()] = float(value)
        except ValueError:
            raise typer.BadParameter(f"--set {what}: expected sensor:number pairs separated by commas, "
                                     f"got {item!r}") from None
    return out


def _parse_set(items: list[str]) -> dict:
    """key=value pairs for any SimConfig field; values parsed as numbers, booleans,
    comma-separated tuples, per-sensor values (``clock_offsets=cam_2:-0.2,cam_5:0.1``)
    or 'none'."""
    from edge_clients.sim import SimConfig

    known = SimConfig.field_names()
    out: dict = {}
    for item in items:
        key, sep, value = item.partition("=")
        key = key.strip().replace("-", "_")
        if not sep:
            raise typer.BadParameter(f"--set {item!r}: expected key=value")
        if key not in known:
            raise typer.BadParameter(f"--set {key}: unknown simulator setting (known: {', '.join(known)})")
        v = value.strip()
        if v.lower() in ("none", "null"):
            out[key] = None
        elif v.lower() in ("true", "false"):
            out[key] = v.lower() == "true"
        elif ":" in v:
            out[key] = _per_sensor(v, key)
        elif "," in v:
            out[key] = _floats(v, key)
        else:
            try:
                out[key] = int(v)
            except ValueError:
                try:
                    out[key] = float(v)
                except ValueError:
                    raise typer.BadParameter(f"--set {key}: {v!r} is not a number") from None
    return out


_HELP = (
    "Simulate people walking through the camera network of CAMERAS and write what the edge "
    "sensors would publish (a recording) plus the ground truth (OUT.truth.npz), then print "
    "the run's figures.\n\n"
    "The sensors are realistic: own capture rates and phases, NTP clock errors, network delays, "
    "pixel noise growing towards wrists and ankles, occlusions, missed and false detections. "
    "The same seed gives the same bytes."
)


def register(app: typer.Typer) -> None:
    @app.command(help=_HELP)
    def simulate(
        out: Annotated[Path, typer.Option(help="recording to write: .jsonl, .jsonl.gz or .msgpack; "
                                                "the ground truth goes to OUT.truth.npz")],
        cameras: Annotated[Path, typer.Option(help="directory with intrinsics.yaml and reference.yaml "
                                                   "(+ optional room.yaml with a floor plan)")] = LAB,
        scene: Annotated[Optional[str], typer.Option(help="a generated scene instead of --cameras: 'corridor' (6 cameras "
                                                         "along a corridor, each overlapping only its neighbours) or "
                                                         "'room' (4 cameras in the corners of a 7 x 5 m room, 100° "
                                                         "distorted lenses); its camera files are written to "
                                                         "OUT.cameras/")] = None,
        persons: Annotated[int, typer.Option(help="people walking", min=0)] = 2,
        duration: Annotated[float, typer.Option(help="seconds of simulated time", min=0.1)] = 180.0,
        seed: int = 0,
        heights: Annotated[Optional[str], typer.Option(help="body heights in m, one per person, e.g. 1.96,1.70 "
                                                            "(default: drawn around 1.75)")] = None,
        noise_scale: Annotated[float, typer.Option(help="multiplies every pixel noise sigma", min=0.0)] = 1.0,
        noise: Annotated[bool, typer.Option(help="detector errors (off: exact projections of visible joints)")] = True,
        start_time: Annotated[float, typer.Option(help="epoch s of simulated t = 0")] = 1.7e9,
        rates: Annotated[Optional[str], typer.Option(help="min,max capture rate Hz of the sensors")] = None,
        camera_height: Annotated[float, typer.Option(help="m of the cameras above the floor; used only without room.yaml")] = 2.6,
        set_: Annotated[Optional[list[str]], typer.Option("--set", help="any simulator setting, key=value "
                                                                        "(e.g. --set miss_prob=0.05); see SimConfig")] = None,
        json_out: Annotated[bool, typer.Option("--json", help="print the figures as JSON")] = False,
    ) -> None:
        import json
        import time

        from backend.cameras import CameraFileError
        from backend.cli import fail
        from edge_clients.sim import Scene, SimConfig, Simulator

        kw = _parse_set(set_ or [])
        if heights:
            kw["heights"] = _floats(heights, "--heights")
        if rates:
            r = _floats(rates, "--rates")
            if len(r) != 2:
                raise fail("--rates: expected min,max")
            kw["rates"] = r
        kw.setdefault("camera_height", camera_height)
        t0 = time.perf_counter()
        try:
            if scene is not None:
                from edge_clients.sim.scenes import make, write_scene

                generated = make(scene)
                cameras = write_scene(generated, Path(f"{out}.cameras"), f"generated scene {scene!r}")
            scene_ = Scene.load(cameras, camera_height=kw["camera_height"])
            config = SimConfig(persons=persons, duration=duration, seed=seed, noise=noise,
                               noise_scale=noise_scale, start_time=start_time, **kw)
            sim = Simulator(scene_, config)
        except (CameraFileError, FileNotFoundError, ValueError, TypeError) as e:
            raise fail(str(e))
        if not json_out:
            typer.echo(f"simulating {duration:g} s of {persons} persons in {cameras} ({len(scene_.names)} cameras)...",
                       err=True)
        stats = sim.write(out)
        wall = time.perf_counter() - t0
        if json_out:
            d = stats.to_dict()
            d["wall_time_s"] = wall
            typer.echo(json.dumps(d, indent=2))
            return
        typer.echo(stats.table())
        typer.echo("")
        typer.echo(f"wrote {out} ({stats.total_messages} messages) and {out}.truth.npz in {wall:.1f} s")
