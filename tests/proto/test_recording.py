"""Recordings: JSON Lines (plain, gzip) and msgpack streams; bad records by line."""

from __future__ import annotations

import gzip
import json

import msgpack
import numpy as np
import pytest

from proto import KeypointMessage, Person, ReadStats, RecordingError, RecordingWriter, read_recording, to_dict, write_recording
from proto import keys


def _messages(n: int = 5) -> list[KeypointMessage]:
    rng = np.random.default_rng(3)
    out = []
    for i in range(n):
        ps = tuple(Person(kp=np.column_stack([rng.uniform(0, 640, 17), rng.uniform(0, 480, 17),
                                              rng.uniform(0, 1, 17)]), bbox=np.array([0.0, 1.0, 2.0, 3.0]),
                          score=0.5) for _ in range(i % 3))
        out.append(KeypointMessage(f"cam_{i % 2}", i, 1.7e9 + 0.05 * i, (640, 480), ps))
    return out


@pytest.mark.parametrize("name", ["rec.jsonl", "rec.jsonl.gz", "rec.msgpack", "rec.mpk", "rec.msgpack.gz"])
def test_round_trip(tmp_path, name):
    msgs = _messages()
    assert write_recording(tmp_path / name, msgs) == len(msgs)
    assert list(read_recording(tmp_path / name)) == msgs


def test_formats_follow_the_name(tmp_path):
    msgs = _messages(2)
    write_recording(tmp_path / "a.jsonl", msgs)
    write_recording(tmp_path / "a.jsonl.gz", msgs)
    write_recording(tmp_path / "a.msgpack", msgs)
    lines = (tmp_path / "a.jsonl").read_text().splitlines()
    assert json.loads(lines[0])["sensor"] == "cam_0" and len(lines) == 2
    assert gzip.decompress((tmp_path / "a.jsonl.gz").read_bytes()).decode().splitlines() == lines
    with open(tmp_path / "a.msgpack", "rb") as f:
        first = next(iter(msgpack.Unpacker(f, raw=False)))
    assert first["seq"] == 0 and isinstance(first["persons"], list)


def test_gzip_bytes_do_not_depend_on_time_or_name(tmp_path):
    msgs = _messages()
    write_recording(tmp_path / "a.jsonl.gz", msgs)
    write_recording(tmp_path / "b.jsonl.gz", msgs)
    assert (tmp_path / "a.jsonl.gz").read_bytes() == (tmp_path / "b.jsonl.gz").read_bytes()


def test_flushed_gzip_is_readable_before_close(tmp_path):
    p = tmp_path / "live.jsonl.gz"
    w = RecordingWriter(p)
    msgs = _messages(3)
    for m in msgs:
        w.write(m)
    w.flush()
    # a reader sees everything flushed; the open member's tail counts as unreadable, not fatal
    stats = ReadStats()
    assert list(read_recording(p, skip_bad=True, stats=stats)) == msgs
    w.close()
    assert list(read_recording(p)) == msgs


def test_append_adds_a_gzip_member(tmp_path):
    p = tmp_path / "a.jsonl.gz"
    msgs = _messages(4)
    write_recording(p, msgs[:2])
    with RecordingWriter(p, append=True) as w:
        for m in msgs[2:]:
            w.write(m)
    assert list(read_recording(p)) == msgs


def _jsonl_with(tmp_path, bad_line: str, at: int = 3):
    msgs = _messages(5)
    lines = [json.dumps(to_dict(m)) for m in msgs]
    lines.insert(at - 1, bad_line)
    p = tmp_path / "bad.jsonl"
    p.write_text("\n".join(lines) + "\n")
    return p, msgs


@pytest.mark.parametrize("bad,reason", [
    ("{not json", "not JSON"),
    ('{"v": 1, "sensor": "cam_0", "seq": 1, "stamp": 1.7e9, "size": [640, 480], '
     '"persons": [{"kp": [[1, 2, 0.5]]}]}', "persons[0].kp: expected 17 rows of 3, got 1"),
    ('{"sensor": "cam_0", "seq": 1, "stamp": "x", "size": [640, 480], "persons": []}', "stamp: expected a number"),
    ("[1, 2, 3]", "expected a map at the top level"),
])
def test_bad_line_is_reported_with_its_number(tmp_path, bad, reason):
    p, msgs = _jsonl_with(tmp_path, bad, at=3)
    it = read_recording(p)
    assert [next(it), next(it)] == msgs[:2]
    with pytest.raises(RecordingError) as e:
        next(it)
    assert e.value.line == 3 and reason in e.value.error
    assert str(e.value).startswith(f"{p}:3: ")


def test_skip_bad_counts(tmp_path):
    msgs = _messages(5)
    lines = [json.dumps(to_dict(m)) for m in msgs]
    lines[1] = "garbage"
    lines[3] = '{"v": 1, "sensor": "cam_0", "seq": -4, "stamp": 1.7e9, "size": [640, 480], "persons": []}'
    lines.insert(2, "")  # blank lines are not records
    p = tmp_path / "r.jsonl"
    p.write_text("\n".join(lines) + "\n")
    stats = ReadStats()
    got = list(read_recording(p, skip_bad=True, stats=stats))
    assert got == [msgs[0], msgs[2], msgs[4]]
    assert stats.read == 3 and stats.skipped == 2
    assert any(":2: not JSON" in e for e in stats.first_errors)
    assert any(":5: seq: must be >= 0" in e for e in stats.first_errors)
    assert stats.reasons == {"not JSON": 1, "seq": 1}


def test_truncated_gzip_tail_ends_the_file(tmp_path):
    p = tmp_path / "t.jsonl.gz"
    write_recording(p, _messages(5))
    raw = p.read_bytes()
    p.write_bytes(raw[: len(raw) - 30])
    with pytest.raises(RecordingError, match="unreadable tail") as e:
        list(read_recording(p))
    assert 1 <= e.value.line <= 6  # the line where the damage starts
    stats = ReadStats()
    got = list(read_recording(p, skip_bad=True, stats=stats))
    assert stats.skipped == 1 and len(got) <= 5


def test_msgpack_garbage_is_reported_with_record_number(tmp_path):
    p = tmp_path / "r.msgpack"
    msgs = _messages(3)
    write_recording(p, msgs)
    with open(p, "ab") as f:
        f.write(msgpack.packb({"v": 1, "sensor": "cam_0", "seq": 9, "stamp": 1.7e9, "size": [640, 480],
                               "persons": [{"kp": [[1, 2, 3]] * 17}]}))
    with pytest.raises(RecordingError) as e:
        list(read_recording(p))
    assert e.value.line == 4 and "persons[0].kp[0]: confidence 3.0 outside [0, 1]" in e.value.error
    stats = ReadStats()
    assert list(read_recording(p, skip_bad=True, stats=stats)) == msgs and stats.skipped == 1


def test_missing_file():
    with pytest.raises(FileNotFoundError, match="does not exist"):
        list(read_recording("/nonexistent/rec.jsonl"))


def test_key_expressions():
    assert keys.keypoints("lab", "cam_3") == "extrcal/lab/sensors/cam_3/keypoints"
    assert keys.all_keypoints("lab") == "extrcal/lab/sensors/*/keypoints"
    assert keys.calibration("default") == "extrcal/default/calibration"
    assert keys.alive("lab", "cam_3") == "extrcal/lab/sensors/cam_3/alive"
    assert keys.sensor_of("extrcal/lab/sensors/cam_3/keypoints") == "cam_3"
    assert keys.sensor_of("extrcal/lab/calibration") is None
    for bad in ("a/b", "*", "", "x$y"):
        with pytest.raises(ValueError, match="must be non-empty"):
            keys.keypoints("lab", bad)
