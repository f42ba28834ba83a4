"""`extrcal demo` end to end, short: simulated lab → Zenoh → service → session → table."""

from __future__ import annotations

import io

import pytest

from backend.cli_service import run_demo

pytestmark = pytest.mark.slow


def test_demo_runs_a_session_and_prints_the_result_table(tmp_path):
    out = io.StringIO()
    session = run_demo(speed=4.0, duration=12.0, http="127.0.0.1:0", persons=2, translation=0.1, rotation=3.0,
                       seed=0, state_dir=tmp_path, until_converged=False, out=out)
    text = out.getvalue()
    assert "service: http://127.0.0.1:" in text and "/status" in text
    assert session["state"] == "stopped" and session["stopped_by"] == "duration", session["reason"]
    assert session["cycles"] >= 1 and len(session["cameras"]) == 20
    # the table: one row per camera, then the summary against the simulator's truth
    assert all(f" cam_{i} " in text for i in range(20))
    assert "initial estimate: position" in text and "result:           position" in text
    assert (tmp_path / "sessions" / session["id"] / "result.yaml").is_file()
    # the initial estimate's scale against the people's, checked when the session stopped
    check = session["scale"]["check"]
    assert check["mode"] == "keep" and check["factor"] == 1.0 and session["scale"]["summary"] in text
