"""The disk holding the state directory fills up on a live service (real Zenoh, real
uvicorn, simulated sensors). As root, the state directory is a real 8 MiB tmpfs that a
filler file fills to the last byte; without the rights to mount one, ENOSPC is raised at
the one function every state file goes through (``backend.session.write_atomic``).
The service keeps calibrating, reports the fault in /status and in the session, keeps
the last good result file intact, and writes again when space is back."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import time

import httpx
import pytest
import yaml

from backend.cameras import parse_extrinsics
from backend.server import ServiceThread
from proto.transport import free_port
from backend.settings import ServiceSettings
from test_faults_live import _live

pytestmark = pytest.mark.slow


def _mount_tmpfs(path) -> bool:
    if os.geteuid() != 0:
        return False
    path.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(path)], capture_output=True)
    return r.returncode == 0


def _fill(path) -> None:
    """Write zeros into ``path`` until the file system is full."""
    with open(path, "wb") as f:
        chunk = b"\0" * 65536
        try:
            while True:
                f.write(chunk)
                f.flush()
        except OSError as e:
            assert e.errno == errno.ENOSPC, e
    # the last partial chunks: fill to the byte
    for n in (4096, 512, 1):
        try:
            with open(path, "ab") as f:
                while True:
                    f.write(b"\0" * n)
                    f.flush()
        except OSError as e:
            assert e.errno == errno.ENOSPC, e


def test_disk_full_is_reported_and_the_last_result_kept(tmp_path, lab_dir, monkeypatch):
    live = _live()
    state = tmp_path / "state"
    mounted = _mount_tmpfs(state)
    full = {"on": False}
    if not mounted:  # no tmpfs: the one acceptable stand-in, ENOSPC at the write boundary
        import backend.session as session_mod

        real = session_mod.write_atomic

        def write_atomic(path, text):
            if full["on"]:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
            return real(path, text)

        monkeypatch.setattr(session_mod, "write_atomic", write_atomic)
    filler = state / "filler"
    try:
        endpoint, site = f"tcp/127.0.0.1:{free_port()}", "diskfull"
        settings = ServiceSettings.load(None, http={"host": "127.0.0.1", "port": 0}, zenoh={"listen": (endpoint,)},
                                        state_dir=state, site=site, clock="data", speed=4.0)
        with ServiceThread(settings) as st, httpx.Client(base_url=st.url, timeout=30) as c, \
                live.Sensors(endpoint, site, lab_dir, seed=7):
            sid = c.post("/sessions", json={**live._session_body(lab_dir), "stop": {"duration": 36000}}).json()["id"]
            live._poll(c, f"/sessions/{sid}", lambda s: s["cycles"] >= 2, 90, "no 2 cycles")
            result = state / "sessions" / sid / "result.yaml"
            live._poll(c, f"/sessions/{sid}", lambda s: result.exists(), 30, "no result written")
            # the fault: the disk is full
            if mounted:
                _fill(filler)
            else:
                full["on"] = True
            s = live._poll(c, f"/sessions/{sid}", lambda s: s["storage_error"] and "No space left" in s["storage_error"],
                           60, "the full disk is not reported")
            at_fault = s["cycles"]
            live._poll(c, "/status", lambda x: "No space left" in (x["storage"]["error"] or "") and x["storage"]["errors"] >= 1,
                       30, "/status does not show the full disk")
            # it goes on calibrating; the result file on disk is the last good one, whole
            s = live._poll(c, f"/sessions/{sid}", lambda s: s["cycles"] >= at_fault + 3, 90, "stalled by the fault")
            assert s["state"] in ("calibrating", "converged") and s["storage_error"]
            kept = result.read_text()
            ext = parse_extrinsics(kept, str(result))
            assert sorted(ext) == sorted(live.CAMS)
            written_cycle = int(kept.split("cycle ")[1].split(",")[0])
            assert written_cycle < s["cycles"]  # not updated while full
            # no temp file left behind: the writer keeps trying, so one may exist for the
            # instant between its creation and its removal; a leaked one stays
            temps = lambda: {p.name for p in result.parent.iterdir() if p.name.endswith(".tmp")}  # noqa: E731
            first = temps()
            time.sleep(0.5)
            assert not first & temps()
            assert c.get("/healthz").json()["ok"] and len(c.get("/calibration").json()["cameras"]) == len(live.CAMS)
            # space is back: writes succeed, the error clears, the result moves on
            if mounted:
                filler.unlink()
            else:
                full["on"] = False
            live._poll(c, f"/sessions/{sid}", lambda s: s["storage_error"] is None, 60, "no recovery")
            # /status may be the snapshot the service published up to a second ago (as_of): poll
            live._poll(c, "/status", lambda x: x["storage"]["error"] is None, 30, "/status still shows the error")
            live._poll(c, f"/sessions/{sid}", lambda s: int(result.read_text().split("cycle ")[1].split(",")[0])
                       > written_cycle, 60, "the result is not written again")
            json.loads((result.parent / "session.json").read_text())
            yaml.safe_load(result.read_text())
    finally:
        if mounted:
            subprocess.run(["umount", "-l", str(state)], check=False)
