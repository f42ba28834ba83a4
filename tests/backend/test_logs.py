"""Structured logs of the daemon."""

from __future__ import annotations

import json
import logging

import pytest

from backend.logs import JsonFormatter, setup


def test_json_lines_carry_level_logger_message_and_extra_fields():
    rec = logging.LogRecord("backend.service", logging.WARNING, __file__, 1, "cycle %d rejected", (7,), None)
    rec.session = "20261121T1200-ab12"
    d = json.loads(JsonFormatter().format(rec))
    assert d["level"] == "warning" and d["logger"] == "backend.service"
    assert d["msg"] == "cycle 7 rejected" and d["session"] == "20261121T1200-ab12"
    assert d["ts"].endswith("Z")


def test_an_unknown_format_is_refused():
    with pytest.raises(ValueError, match="text or json"):
        setup("info", "xml")
