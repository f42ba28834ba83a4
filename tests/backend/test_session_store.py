"""Sessions on disk: records, camera files, history journal, resume inputs."""

from __future__ import annotations

import json

import pytest

from backend.config import EngineConfig
from backend.session import (
    SessionInputError, SessionInputs, SessionNotFound, SessionRecord, SessionState, SessionStore, StopCriteria,
    new_session_id,
)


@pytest.fixture()
def lab_texts(lab_dir):
    return (lab_dir / "intrinsics.yaml").read_text(), (lab_dir / "reference.yaml").read_text()


def _record(**kw) -> SessionRecord:
    return SessionRecord(id=new_session_id(), name="t", state=SessionState.waiting_for_data, reason="",
                         stop=StopCriteria(duration=60, converged=True), config_overrides={"select": {"scope": 40}},
                         sources={"intrinsics": "upload"}, **kw)


def test_create_load_roundtrip(tmp_path, lab_texts):
    intr, ref = lab_texts
    cfg = EngineConfig().merged({"select": {"scope": 40}})
    inputs = SessionInputs.parse(intr, ref, ref, cfg)
    assert len(inputs.cameras.names) == 20 and inputs.reference is not None
    store = SessionStore(tmp_path)
    rec = _record()
    store.create(rec, inputs)
    assert store.ids() == [rec.id]
    back = store.load_record(rec.id)
    assert back.to_dict() == rec.to_dict()
    again = store.load_inputs(back)
    assert again.config.select.scope == 40 and again.cameras.names == inputs.cameras.names
    assert again.reference is not None and set(again.reference) == set(inputs.reference)
    with pytest.raises(SessionNotFound):
        store.load_record("20990101T000000-abcd")
    with pytest.raises(SessionNotFound):
        store.dir("../../etc")  # ids are checked before they touch the file system


def test_the_px_parameters_are_in_the_keypoints_pixels_and_survive_a_resume(tmp_path, lab_texts):
    """Intrinsics of 2x the lab's size whose detector publishes at the lab's size (the
    initial estimate's resolution): the px parameters stay the lab's; without an initial
    estimate (messages at the intrinsics' size) they double; a resume does not scale again."""
    import yaml

    intr, ref = lab_texts
    big = yaml.safe_load(intr)
    for v in big.values():
        v["intrinsics"] = [2 * x for x in v["intrinsics"]]
        v["resolution"] = [2 * x for x in v["resolution"]]
    big_text = yaml.safe_dump(big)
    base = EngineConfig().associate.gate_pixels
    assert SessionInputs.parse(big_text, ref, None, EngineConfig()).config.associate.gate_pixels == base
    alone = SessionInputs.parse(big_text, None, None, EngineConfig())
    assert alone.config.associate.gate_pixels == pytest.approx(2 * base)
    store = SessionStore(tmp_path)
    rec = _record()
    store.create(rec, alone)
    assert store.load_inputs(store.load_record(rec.id)).config.associate.gate_pixels == pytest.approx(2 * base)


def test_ids_sort_in_the_order_sessions_were_made_even_within_one_second(tmp_path, lab_texts, monkeypatch):
    """A stop and a start from a script make two sessions in one second; the list and the
    report take "newest" from the order of ids, so the random suffix must not decide it."""
    import time as _time

    intr, ref = lab_texts
    store = SessionStore(tmp_path)
    inputs = SessionInputs.parse(intr, ref, None, EngineConfig())
    old = tmp_path / "20260101T000000-ffff"  # an id of an older version, without milliseconds
    store.create(SessionRecord.from_dict({**_record().to_dict(), "id": old.name}), inputs)
    base = 1_800_000_000_000_000_000  # one second, three sessions in it
    made = []
    for k, ms in enumerate((5, 250, 999)):
        monkeypatch.setattr(_time, "time_ns", lambda ms=ms: base + ms * 1_000_000)
        rec = SessionRecord.from_dict({**_record().to_dict(), "id": new_session_id()})
        store.create(rec, inputs)
        made.append(rec.id)
    assert len({m.split(".")[0] for m in made}) == 1  # the same second
    assert store.ids() == [old.name, *made]


def test_history_drops_a_torn_line_and_is_cut_on_resume(tmp_path, lab_texts):
    intr, ref = lab_texts
    store = SessionStore(tmp_path)
    rec = _record()
    store.create(rec, SessionInputs.parse(intr, ref, None, EngineConfig()))
    store.append_history(rec.id, [{"cycle": i, "x": i * 0.5} for i in range(1, 6)])
    with open(store.dir(rec.id) / "history.jsonl", "ab") as f:
        f.write(b'{"cycle": 6, "x": 3.')  # SIGKILL in the middle of a write
    assert [h["cycle"] for h in store.history(rec.id)] == [1, 2, 3, 4, 5]
    assert [h["cycle"] for h in store.history(rec.id, since=3)] == [4, 5]
    assert store.cut_history(rec.id, 3) == 3
    text = (store.dir(rec.id) / "history.jsonl").read_text()
    assert text.endswith("\n") and [json.loads(x)["cycle"] for x in text.splitlines()] == [1, 2, 3]
    store.append_history(rec.id, [{"cycle": 4}])
    assert [h["cycle"] for h in store.history(rec.id)] == [1, 2, 3, 4]


def test_nan_is_written_as_null(tmp_path, lab_texts):
    intr, ref = lab_texts
    store = SessionStore(tmp_path)
    rec = _record()
    store.create(rec, SessionInputs.parse(intr, ref, None, EngineConfig()))
    store.save_result(rec.id, "cam_0: {}\n", {"cameras": [{"change_translation": float("inf")}], "x": float("nan")})
    assert store.load_state(rec.id) == {"cameras": [{"change_translation": None}], "x": None}


@pytest.mark.parametrize("which, text, needle", [
    ("intrinsics", "cam_0: [1, 2", "intrinsics_yaml:1"),
    ("initial", "cam_0:\n  translation: [0, 0]\n  rotation: [0, 0, 0, 1]\n", "initial_yaml:2: cam_0.translation"),
    ("initial", "cam_0:\n  translation: [0, 0, 0]\n  rotation: [0, 0, 0, 1]\n", "camera sets differ"),
    ("reference", "cam_99:\n  translation: [0, 0, 0]\n  rotation: [0, 0, 0, 1]\n", "not in the camera set"),
])
def test_bad_camera_files_name_file_line_field(lab_texts, which, text, needle):
    intr, ref = lab_texts
    args = {"intrinsics": intr, "initial": ref, "reference": None}
    args[which] = text
    with pytest.raises(SessionInputError, match=needle.replace("[", r"\[").replace(".", r"\.")):
        SessionInputs.parse(args["intrinsics"], args["initial"], args["reference"], EngineConfig())
