"""Edge commands: `extrcal sensor sim|camera`, `extrcal replay`, `extrcal record`.

Every command that talks Zenoh takes the same flags as `extrcal serve` (the aliases
below): --zenoh-listen, --zenoh-connect, --zenoh-mode, --zenoh-config, --site. A
sensor given none of them connects as a peer to tcp/127.0.0.1:7447 (a backend or a
zenohd on the same host), with multicast scouting off.

Heavy imports (OpenCV, detectors, Zenoh) happen inside the commands: the base install
runs sim, replay and record.
"""

from __future__ import annotations

import dataclasses
import math
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Optional

import typer

from proto.keys import DEFAULT_SITE

DEFAULT_CONNECT = "tcp/127.0.0.1:7447"
SIM_START_DELAY = 2.0  # s between `extrcal sensor sim` starting and simulated time 0

# ---------------------------------------------------------------- shared flags

ZenohListen = Annotated[Optional[list[str]], typer.Option(
    "--zenoh-listen", metavar="ENDPOINT",
    help="Zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7448 (repeatable)", rich_help_panel="Zenoh")]
ZenohConnect = Annotated[Optional[list[str]], typer.Option(
    "--zenoh-connect", metavar="ENDPOINT",
    help=f"Zenoh endpoint to connect to: the backend or a zenohd router (repeatable; default "
         f"{DEFAULT_CONNECT} unless --zenoh-listen or --zenoh-config is given)", rich_help_panel="Zenoh")]
ZenohMode = Annotated[str, typer.Option(
    "--zenoh-mode", help="peer, client (through a router) or router", rich_help_panel="Zenoh")]
ZenohConfig = Annotated[Optional[Path], typer.Option(
    "--zenoh-config", exists=True, dir_okay=False,
    help="a full Zenoh JSON5 config (TLS, access control); the flags above override it", rich_help_panel="Zenoh")]
Site = Annotated[str, typer.Option(
    "--site", envvar="EXTRCAL_SITE", help="<site> in extrcal/<site>/sensors/<sensor>/...", rich_help_panel="Zenoh")]

NtpServer = Annotated[Optional[str], typer.Option(
    "--ntp-server", metavar="HOST[:PORT]", help="check this host's clock against an NTP server every --ntp-interval s",
    rich_help_panel="Clock")]
NtpInterval = Annotated[float, typer.Option("--ntp-interval", min=1.0, help="s between NTP checks", rich_help_panel="Clock")]
ClockCorrect = Annotated[bool, typer.Option(
    "--clock-correct", help="add the measured NTP offset to every stamp (otherwise it is only reported)",
    rich_help_panel="Clock")]
Quiet = Annotated[bool, typer.Option("--quiet", "-q", help="no status line")]


def zenoh_settings(listen: list[str] | None, connect: list[str] | None, mode: str,
                   config: Path | None):
    """ZenohSettings from the shared flags, with the sensors' default endpoint."""
    from proto.transport import ZenohSettings

    if mode not in ("peer", "client", "router"):
        raise typer.BadParameter(f"expected peer, client or router, got {mode!r}", param_hint="--zenoh-mode")
    connect = list(connect or [])
    if not connect and not listen and config is None:
        connect = [DEFAULT_CONNECT]
    return ZenohSettings(mode=mode, listen=tuple(listen or ()), connect=tuple(connect),
                         config_file=str(config) if config else None)


def _fail(message: str, code: int = 2) -> typer.Exit:
    typer.secho(f"error: {message}", err=True, fg=typer.colors.RED)
    return typer.Exit(code)


def _check_site(site: str) -> None:
    from proto import keys

    try:
        keys.keypoints(site, "x")
    except ValueError as e:
        raise typer.BadParameter(str(e), param_hint="--site") from None


def _clock(ntp_server: str | None, correct: bool, interval: float):
    from .clock import make_clock

    try:
        return make_clock(ntp_server, correct=correct, interval=interval)
    except ValueError as e:
        raise _fail(str(e)) from None


@contextmanager
def _open(settings):
    """The Zenoh session, closed explicitly; a failure to open is one clear error."""
    from proto.transport import open_session

    try:
        session = open_session(settings)
    except Exception as e:  # zenoh.ZError: a bad endpoint, a port in use, a bad config
        raise _fail(f"cannot open the Zenoh session ({e})") from None
    try:
        yield session
    finally:
        session.close()


# ---------------------------------------------------------------- commands

sensor_app = typer.Typer(
    name="sensor", no_args_is_help=True,
    help="Run edge sensors that publish keypoint messages: simulated ones, or a camera with a pose detector.",
)


@sensor_app.command("sim")
def sensor_sim(
    cameras: Annotated[Path, typer.Option("--cameras", help="scene folder: intrinsics.yaml, reference.yaml (the true poses), optional room.yaml",
                                          exists=True, file_okay=False)],
    sensor: Annotated[Optional[list[str]], typer.Option("--sensor", help="sensor to run (repeatable), or 'all' (default)")] = None,
    persons: Annotated[int, typer.Option(min=0, help="people walking")] = 2,
    seed: int = 0,
    speed: Annotated[float, typer.Option(help="K: publish K× faster than real time (stamps keep the simulated spacing)")] = 1.0,
    duration: Annotated[Optional[float], typer.Option(help="s of simulated time (default: until stopped)")] = None,
    start_at: Annotated[Optional[float], typer.Option(
        help=f"epoch s at which simulated time starts (default: in {SIM_START_DELAY:.0f} s); give all processes of one run the same value")] = None,
    wait_subscriber: Annotated[float, typer.Option(help="s to wait for a subscriber (backend, recorder) before starting; 0: don't")] = 0.0,
    zenoh_listen: ZenohListen = None,
    zenoh_connect: ZenohConnect = None,
    zenoh_mode: ZenohMode = "peer",
    zenoh_config: ZenohConfig = None,
    site: Site = DEFAULT_SITE,
    ntp_server: NtpServer = None,
    ntp_interval: NtpInterval = 64.0,
    clock_correct: ClockCorrect = False,
    quiet: Quiet = False,
) -> None:
    """Publish simulated sensors live: people walk through the scene, each sensor with its own
    clock error, capture rate and detector noise. One process per sensor (--sensor cam_3) sends
    exactly that sensor's messages of the all-sensor run with the same --seed and --start-at."""
    from .publisher import SensorPublisher, StatusLine, format_rate_summary, stop_on_signals
    from .sim import Scene, SimConfig, Simulator

    _check_site(site)
    if speed <= 0:
        raise typer.BadParameter("must be > 0", param_hint="--speed")
    try:
        scene = Scene.load(cameras)
    except (OSError, ValueError) as e:
        raise _fail(str(e)) from None
    names = _pick_sensors(sensor, scene.names)
    settings = zenoh_settings(zenoh_listen, zenoh_connect, zenoh_mode, zenoh_config)
    with _clock(ntp_server, clock_correct, ntp_interval) as clock, _open(settings) as session, \
            SensorPublisher(session, site, block=True) as pub, stop_on_signals() as stop:
        origin = clock.now() if start_at is None else start_at
        try:
            config = SimConfig(persons=persons, seed=seed, duration=math.inf if duration is None else duration,
                               start_time=origin)
        except ValueError as e:
            raise _fail(str(e)) from None
        for n in names:
            pub.declare(n)  # liveliness from the start, not from the first frame
        if wait_subscriber > 0 and not pub.wait_matched(names, wait_subscriber, stop):
            typer.echo(f"no subscriber after {wait_subscriber} s; publishing anyway", err=True)
        if start_at is None:
            # After the wait, and leaving the simulator time to warm up: simulated time 0
            # is just ahead, so the first messages are not late.
            origin = clock.now() + SIM_START_DELAY
            config = dataclasses.replace(config, start_time=origin)
        status = StatusLine(lambda: f"sim: {pub.total} sent — {format_rate_summary(pub.stats)}; {clock.status()}",
                            enabled=not quiet)
        with status:
            paced = run_sim(pub, Simulator(scene, config), names, origin=origin, speed=speed, now=clock.now,
                            stop=stop, on_message=status.update)
    typer.echo(f"sent {pub.total} messages from {len(names)} sensors in {paced.seconds:.1f} s"
               + (", stopped" if paced.stopped else ""))
    if paced.max_late > 0.5:
        typer.echo(f"fell behind real time by up to {paced.max_late:.2f} s (lower --speed or run fewer sensors per process)")


def _pick_sensors(chosen: list[str] | None, known: tuple[str, ...]) -> list[str]:
    if not chosen or chosen == ["all"]:
        return list(known)
    unknown = [s for s in chosen if s not in known]
    if unknown:
        raise typer.BadParameter(f"unknown {', '.join(unknown)}; the scene has {', '.join(known)}", param_hint="--sensor")
    return list(dict.fromkeys(chosen))


def run_sim(publisher, simulator, sensors: list[str] | None, *, origin: float, speed: float = 1.0,
            now=None, stop=None, on_message=None):
    """Publish the simulator's messages of ``sensors`` when they arrive: the simulator's
    arrival times are epoch s from ``origin`` (its start_time); ``now`` is the sensor's clock."""
    import itertools
    import time

    from .publisher import publish_paced

    now = now or time.time
    it = simulator.messages(sensors)
    first = next(it, None)  # the simulator warms up (world, first frames) before the clock runs
    head = [] if first is None else [first]
    items = ((arrival - origin, msg) for arrival, msg in itertools.chain(head, it))
    return publish_paced(publisher, items, speed=speed, start_mono=time.monotonic() + (origin - now()),
                         stop=stop, on_message=on_message)


@sensor_app.command("camera")
def sensor_camera(
    sensor: Annotated[str, typer.Option("--sensor", help="sensor id = the camera's key in the camera files (cam_3)")],
    source: Annotated[str, typer.Option("--source", help="device index (0), stream URL (rtsp://...) or video file")] = "0",
    detector: Annotated[str, typer.Option(
        "--detector", help="mediapipe | onnx:MODEL.onnx | package.module:Class (your plugin)")] = "mediapipe",
    detector_arg: Annotated[Optional[list[str]], typer.Option(
        "--detector-arg", metavar="KEY=VALUE", help="keyword argument for the detector (repeatable)")] = None,
    max_fps: Annotated[Optional[float], typer.Option(help="capture at most this many frames per second")] = None,
    frames: Annotated[Optional[int], typer.Option(help="stop after this many frames")] = None,
    realtime: Annotated[bool, typer.Option(help="a video file plays at its own frame rate instead of as fast as possible")] = False,
    capture_latency: Annotated[float, typer.Option(min=0.0, help="s from exposure to grab() returning, subtracted from stamps")] = 0.0,
    wait_subscriber: Annotated[float, typer.Option(help="s to wait for a subscriber (backend, recorder) before capturing; 0: don't")] = 0.0,
    zenoh_listen: ZenohListen = None,
    zenoh_connect: ZenohConnect = None,
    zenoh_mode: ZenohMode = "peer",
    zenoh_config: ZenohConfig = None,
    site: Site = DEFAULT_SITE,
    ntp_server: NtpServer = None,
    ntp_interval: NtpInterval = 64.0,
    clock_correct: ClockCorrect = False,
    quiet: Quiet = False,
) -> None:
    """Capture with OpenCV, detect persons (COCO-17 keypoints) and publish them stamped with
    the capture time. Needs the [camera] extra and a detector's extra ([mediapipe] or [onnx])."""
    _check_site(site)
    try:
        import cv2  # noqa: F401
    except ImportError:
        raise _fail("the camera client needs OpenCV: pip install 'extrcal[camera]'") from None
    from .camera import CameraError, run_camera_cli
    from .detectors import DetectorError, load_detector

    try:
        det = load_detector(detector, _kwargs(detector_arg))
    except DetectorError as e:
        raise _fail(str(e)) from None
    settings = zenoh_settings(zenoh_listen, zenoh_connect, zenoh_mode, zenoh_config)
    try:
        with _clock(ntp_server, clock_correct, ntp_interval) as clock, _open(settings) as session:
            run_camera_cli(session, sensor=sensor, source=source, detector=det, site=site, clock=clock,
                           max_fps=max_fps, frames=frames, realtime=realtime, quiet=quiet,
                           capture_latency=capture_latency, wait_subscriber=wait_subscriber)
    except (CameraError, DetectorError) as e:
        raise _fail(str(e)) from None
    finally:
        close = getattr(det, "close", None)
        if close:
            close()


def _kwargs(items: list[str] | None) -> dict:
    import json

    out = {}
    for item in items or []:
        if "=" not in item:
            raise typer.BadParameter(f"expected KEY=VALUE, got {item!r}", param_hint="--detector-arg")
        k, v = item.split("=", 1)
        try:
            out[k] = json.loads(v)  # numbers, booleans, lists
        except json.JSONDecodeError:
            out[k] = v
    return out


def replay(
    recording: Annotated[Path, typer.Argument(help="JSON Lines (.jsonl, .jsonl.gz) or msgpack (.msgpack, .mpk) recording",
                                              exists=True, dir_okay=False)],
    speed: Annotated[float, typer.Option(help="K: replay K× faster (stamps keep the recorded spacing); 0 = as fast as possible")] = 1.0,
    loop: Annotated[bool, typer.Option(help="start over at the end, stamps shifted again, seq continuing")] = False,
    sensors: Annotated[Optional[list[str]], typer.Option("--sensors", help="only these sensors (repeatable)")] = None,
    skip_bad: Annotated[bool, typer.Option(help="skip and count bad records instead of refusing the file")] = False,
    check: Annotated[bool, typer.Option(help="validate the whole file before sending anything")] = True,
    start_at: Annotated[Optional[float], typer.Option(help="epoch s the recording's start is mapped to (default: now)")] = None,
    max_gap: Annotated[float, typer.Option(help="s: longer silences or clock steps are shortened to nothing")] = 10.0,
    wait_subscriber: Annotated[float, typer.Option(help="s to wait for a subscriber (backend, recorder) before sending; 0: don't")] = 0.0,
    zenoh_listen: ZenohListen = None,
    zenoh_connect: ZenohConnect = None,
    zenoh_mode: ZenohMode = "peer",
    zenoh_config: ZenohConfig = None,
    site: Site = DEFAULT_SITE,
    quiet: Quiet = False,
) -> None:
    """Publish a recording with its original timing, stamps shifted to now (one shift for all
    sensors, so their relative timing and clock offsets are kept), and report what was sent."""
    from proto import RecordingError

    from .publisher import SensorPublisher, StatusLine, format_rate_summary, stop_on_signals
    from .replay import check_recording, run_replay

    _check_site(site)
    try:
        if check:
            summary = check_recording(recording, skip_bad=skip_bad)
            if not summary.messages:
                raise _fail(f"{recording}: no valid messages")
            if not quiet:
                typer.echo(f"{recording}: {summary.messages} messages from {len(summary.sensors)} sensors"
                           + (f", {summary.stats.skipped} bad records will be skipped" if summary.stats.skipped else ""),
                           err=True)
    except RecordingError as e:
        raise _fail(f"{e} (--skip-bad skips bad records)") from None
    settings = zenoh_settings(zenoh_listen, zenoh_connect, zenoh_mode, zenoh_config)
    with _open(settings) as session, SensorPublisher(session, site, block=True) as pub, stop_on_signals() as stop:
        if wait_subscriber > 0:
            names = sensors or (sorted(summary.sensors) if check else [])
            if names and not pub.wait_matched(names, wait_subscriber, stop):
                typer.echo(f"no subscriber after {wait_subscriber} s; sending anyway", err=True)
        status = StatusLine(lambda: f"replay: {pub.total} sent — {format_rate_summary(pub.stats)}", enabled=not quiet)
        try:
            with status:
                report = run_replay(pub, recording, speed=speed, loop=loop, sensors=sensors, skip_bad=skip_bad,
                                    start_at=start_at, max_gap=max_gap, stop=stop, on_message=status.update)
        except RecordingError as e:
            raise _fail(str(e)) from None
    for line in report.lines():
        typer.echo(line)


def record(
    out: Annotated[Path, typer.Option("--out", help="recording to write: .jsonl, .jsonl.gz, .msgpack or .mpk")],
    duration: Annotated[Optional[float], typer.Option(help="s to record (default: until Ctrl-C / SIGTERM)")] = None,
    sensors: Annotated[Optional[list[str]], typer.Option("--sensors", help="only these sensors (repeatable)")] = None,
    append: Annotated[bool, typer.Option(help="append to an existing recording")] = False,
    queue: Annotated[int, typer.Option(min=10, help="messages waiting to be written before new ones are dropped")] = 20000,
    zenoh_listen: ZenohListen = None,
    zenoh_connect: ZenohConnect = None,
    zenoh_mode: ZenohMode = "peer",
    zenoh_config: ZenohConfig = None,
    site: Site = DEFAULT_SITE,
    quiet: Quiet = False,
) -> None:
    """Record every keypoint message of the site (validated; invalid ones are counted and
    reported), flushed every second so a crash loses at most the last second."""
    from .publisher import StatusLine, stop_on_signals
    from .record import Recorder

    _check_site(site)
    if out.exists() and not append:
        raise _fail(f"{out} exists (use --append, or another name)")
    if not out.parent.is_dir():
        raise _fail(f"folder {out.parent} does not exist")
    settings = zenoh_settings(zenoh_listen, zenoh_connect, zenoh_mode, zenoh_config)
    with _open(settings) as session, stop_on_signals() as stop:
        rec = Recorder(session, out, site=site, sensors=sensors, queue_size=queue, append=append)
        rep = rec.report
        status = StatusLine(
            lambda: f"record: {rep.total} written from {len(rep.written)} sensors"
                    + (f", {sum(rep.rejected.values())} rejected" if rep.rejected else ""),
            enabled=not quiet)
        with status:
            report = rec.run(stop, duration=duration, on_tick=status.update)
    for line in report.lines():
        typer.echo(line)


def register(app: typer.Typer) -> None:
    app.add_typer(sensor_app, name="sensor")
    app.command("replay")(replay)
    app.command("record")(record)
