"""The dashboard on a real service (uvicorn, Zenoh on loopback) fed by real simulated
sensors (`extrcal sensor sim` in a subprocess), looked at in a real headless Chromium."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from backend.cameras import dump_extrinsics, load_extrinsics
from backend.perturb import perturb_extrinsics
from backend.server import ServiceThread
from proto.transport import free_port
from backend.settings import ServiceSettings

TOKEN = "dash-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SITE = "dashtest"
CHROMIUM, CHROMEDRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"


@pytest.fixture(scope="module")
def svc(tmp_path_factory, lab_dir):
    port = free_port()
    files = tmp_path_factory.mktemp("cameras")
    initial = perturb_extrinsics(load_extrinsics(lab_dir / "reference.yaml"), 0.25, 10.0, seed=2)
    (files / "initial.yaml").write_text(dump_extrinsics(initial))
    # the page's Start without uploads uses the server's default camera files
    settings = ServiceSettings.load(
        None, http={"host": "127.0.0.1", "port": 0}, zenoh={"listen": (f"tcp/127.0.0.1:{port}",)},
        state_dir=tmp_path_factory.mktemp("state"), token=TOKEN, site=SITE, clock="data",
        camera_files={"lab_intrinsics": lab_dir / "intrinsics.yaml", "lab_initial": files / "initial.yaml"},
        defaults={"intrinsics": "lab_intrinsics", "initial": "lab_initial"},
    )
    with ServiceThread(settings) as st:
        st.zenoh_endpoint = f"tcp/127.0.0.1:{port}"
        yield st


@pytest.fixture(scope="module")
def session_body(lab_dir):
    initial = perturb_extrinsics(load_extrinsics(lab_dir / "reference.yaml"), 0.25, 10.0, seed=1)
    return {"name": "dashboard test", "intrinsics_yaml": (lab_dir / "intrinsics.yaml").read_text(),
            "initial_yaml": dump_extrinsics(initial), "reference_yaml": (lab_dir / "reference.yaml").read_text(),
            "config": {"select": {"scope": 30}}}


def _stop_all(client, wait: bool = True):
    for s in client.get("/sessions").json():
        if s["state"] in ("waiting_for_data", "calibrating", "converged"):
            client.post(f"/sessions/{s['id']}/stop", headers=AUTH, params={"wait": wait})


def test_page_assets_and_camera_files(svc, session_body):
    with httpx.Client(base_url=svc.url, timeout=30) as c:
        r = c.get("/")
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
        html = r.text
        # every asset is served by the service itself, nothing from another host
        refs = re.findall(r"""(?:src|href)=["']([^"']+)["']""", html)
        assert refs and all(u.startswith("/dashboard/") for u in refs), refs
        for u in refs:
            a = c.get(u)
            assert a.status_code == 200 and len(a.content) > 500, u
            assert not re.search(r"https?://", a.text), f"{u} references another host"
        assert c.get("/dashboard/dashboard.js").headers["content-type"].startswith("text/javascript")
        assert c.get("/dashboard/nope.js").status_code == 404
        assert c.get("/dashboard/..%2Fapi%2Fdashboard.py").status_code == 404
        _stop_all(c)
        sid = c.post("/sessions", headers=AUTH, json=session_body).json()["id"]
        try:
            files = c.get(f"/dashboard/api/sessions/{sid}/cameras").json()
            assert len(files["initial"]) == len(files["reference"]) == len(files["intrinsics"]) == 20
            ref = load_extrinsics_text(session_body["reference_yaml"])
            assert files["reference"]["cam_5"]["translation"] == pytest.approx(ref["cam_5"].pose.t.tolist())
            assert files["intrinsics"]["cam_4"]["width"] == 640
            assert c.get("/dashboard/api/sessions/20990101T000000-abcd/cameras").status_code == 404
        finally:
            c.post(f"/sessions/{sid}/stop", headers=AUTH)


def load_extrinsics_text(text: str):
    from backend.cameras import parse_extrinsics

    return parse_extrinsics(text)


def _chrome(tmp_path: Path):
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium (the test extra) is not installed")
    if not (Path(CHROMIUM).exists() and Path(CHROMEDRIVER).exists()):
        pytest.skip("Debian's chromium and chromium-driver are not installed (apt-get install chromium chromium-driver)")
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--disable-dev-shm-usage", f"--user-data-dir={tmp_path / 'chromium-profile'}",
                 "--window-size=1400,1500"):
        opts.add_argument(flag)
    return webdriver.Chrome(service=Service(executable_path=CHROMEDRIVER), options=opts)


def _wait(pred, timeout: float, what: str, interval: float = 0.25):
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        last = pred()
        if last:
            return last
        time.sleep(interval)
    pytest.fail(f"timed out after {timeout:.0f} s waiting for {what} (last: {last!r})")


@pytest.mark.slow
def test_dashboard_in_chromium_while_a_simulated_session_runs(svc, session_body, lab_dir, tmp_path):
    # first: it skips without chromium, and a client opened before would be left unclosed
    driver = _chrome(tmp_path)
    client = httpx.Client(base_url=svc.url, timeout=30)
    _stop_all(client)
    sid = client.post("/sessions", headers=AUTH, json=session_body).json()["id"]
    sim_log = open(tmp_path / "sim.log", "w")
    sim = subprocess.Popen(
        [sys.executable, "-c", "from backend.cli import main; main()", "sensor", "sim", "--cameras", str(lab_dir),
         "--zenoh-connect", svc.zenoh_endpoint, "--site", SITE, "--persons", "3", "--speed", "2",
         "--duration", "600", "--quiet"],
        stdout=sim_log, stderr=subprocess.STDOUT)
    try:
        driver.get(svc.url + "/")
        by = __import__("selenium.webdriver.common.by", fromlist=["By"]).By
        js = driver.execute_script

        # the page shows the cameras: 20 table rows and 20 frusta of each set
        _wait(lambda: len(driver.find_elements(by.CSS_SELECTOR, "#cameras tbody tr")) == 20, 30, "the camera table")
        drawn = _wait(lambda: (d := js("return document.getElementById('room').dataset.drawn")) and
                      json.loads(d).get("current") == 20 and json.loads(d), 30, "the frusta")
        assert drawn["initial"] == 20 and drawn["reference"] == 20
        assert driver.find_element(by.ID, "session-name").text == "dashboard test"

        # it updates while the session runs: the cycle count in the header goes up, the
        # charts fill, cameras get observations
        def cycle() -> int:
            t = js("return document.getElementById('cycle').textContent")
            return int(t) if t.isdigit() else -1

        def table() -> str:  # read in one go: the page re-renders the rows
            return js("return document.querySelector('#cameras tbody').innerText")

        def observations() -> int:
            return js("return [...document.querySelectorAll('#cameras tbody td:nth-child(2)')]"
                      ".reduce((a, td) => a + (parseInt(td.textContent) || 0), 0)")

        first = _wait(lambda: cycle() >= 1 and cycle(), 240, "the first cycle on the page")
        before = table()
        _wait(lambda: cycle() > first, 180, f"a cycle after {first} on the page")
        assert driver.find_element(by.ID, "conn").text == "live"
        assert int(js("return document.getElementById('chart-change').dataset.points")) > 0
        assert int(js("return document.getElementById('chart-error').dataset.points")) > 0
        _wait(lambda: table() != before, 120, "the camera table to change")
        # /metrics of the same service (backend.metrics, mounted by create_app)
        from prometheus_client.parser import text_string_to_metric_families

        fams = {f.name: f for f in text_string_to_metric_families(client.get("/metrics").text)}
        msgs = {s.labels["sensor"]: s.value for s in fams["extrcal_messages"].samples if s.name.endswith("_total")}
        assert len(msgs) == 20 and min(msgs.values()) > 0
        stds = [s.value for s in fams["extrcal_camera_std_translation_meters"].samples]
        assert len(stds) == 20 and all(v > 0 for v in stds)
        assert fams["extrcal_cycle"].samples[0].value >= first
        obs = observations()
        _wait(lambda: observations() > obs, 180, "observations to grow")

        # each sensor's warnings from /status are marked in its row, the words on hover
        def warned_on_page() -> dict:
            return js("return Object.fromEntries([...document.querySelectorAll('#cameras tbody tr')]"
                      ".map(tr => [tr.dataset.camera, tr.lastElementChild.title]).filter(e => e[1]))")

        def warned_in_status() -> dict:
            sensors = client.get("/status").json()["sensors"]
            return {n: "\n".join(x["warnings"]) for n, x in sensors.items() if x["warnings"]}

        _wait(lambda: warned_on_page() == warned_in_status(), 30, "the page's warnings to be the status'")
        assert driver.find_element(by.ID, "session-state").text in ("calibrating", "converged")
        shot = tmp_path / "dashboard.png"
        assert driver.save_screenshot(str(shot)) and shot.stat().st_size > 20_000
        if os.environ.get("EXTRCAL_ARTIFACTS"):
            Path(os.environ["EXTRCAL_ARTIFACTS"]).mkdir(parents=True, exist_ok=True)
            shutil.copy(shot, Path(os.environ["EXTRCAL_ARTIFACTS"]) / "dashboard.png")

        # the controls: without the token Stop is refused, with it the session stops
        driver.find_element(by.ID, "stop").click()
        _wait(lambda: "token" in driver.find_element(by.ID, "message").text, 20, "the token error")
        tok = driver.find_element(by.ID, "token")
        tok.send_keys(TOKEN)
        js("document.getElementById('token').dispatchEvent(new Event('change'))")
        driver.find_element(by.ID, "stop").click()
        _wait(lambda: client.get(f"/sessions/{sid}").json()["state"] == "stopped", 120, "the session to stop")
        # the report reads what the live service wrote for this session
        from backend.report import load_session, render_html

        data = load_session(svc.service.store.dir(sid))
        assert data.title == "dashboard test" and len(data.camera_names) == 20
        assert data.cycles and data.cycles[-1].cycle >= first + 1
        assert data.result and data.initial and data.reference and data.config
        assert any(c.error_position is not None for c in data.cycles)
        assert all(c.std_translation for c in data.cycles)
        html = render_html(data)
        assert 'id="camera-plot"' in html and "Error vs reference" in html
        (tmp_path / "report.html").write_text(html)
        if os.environ.get("EXTRCAL_ARTIFACTS"):
            shutil.copy(tmp_path / "report.html", Path(os.environ["EXTRCAL_ARTIFACTS"]) / "report.html")
        latest = load_session(svc.settings.state_dir)  # a state directory: its latest session
        assert latest.source == svc.service.store.dir(sid) and latest.cycles == data.cycles
        # the service's exports (backend.export) of this result read back to the same poses
        import tomllib

        import cv2

        r = client.get(f"/sessions/{sid}/result", params={"format": "pose2sim"})
        assert r.status_code == 200 and r.headers["content-type"].startswith("application/toml")
        calib = tomllib.loads(r.text)
        for name, e in data.result.items():
            Rwc = cv2.Rodrigues(np.array(calib[name]["rotation"]))[0]
            assert np.abs(Rwc.T - e.pose.R).max() < 1e-9
            assert np.abs(-Rwc.T @ np.array(calib[name]["translation"]) - e.pose.t).max() < 1e-9
        r = client.get(f"/sessions/{sid}/result", params={"format": "colmap"})
        assert r.status_code == 200 and r.content[:2] == b"PK"
        _wait(lambda: driver.find_element(by.ID, "start").is_enabled(), 30, "Start to be enabled again")
        driver.find_element(by.ID, "name").send_keys("from the page")
        driver.find_element(by.ID, "start").click()
        new = _wait(lambda: (s := client.get("/sessions").json()[0])["id"] != sid and s, 30,
                    f"a new session (page says {driver.find_element(by.ID, 'message').text!r})")
        assert new["name"] == "from the page"
        _wait(lambda: driver.find_element(by.ID, "session-name").text == "from the page", 30, "the page to follow it")
    finally:
        sim.terminate()
        try:
            sim.wait(20)
        except subprocess.TimeoutExpired:
            sim.kill()
            sim.wait()
        sim_log.close()
        driver.quit()
        _stop_all(client, wait=False)
        client.close()
