"""Property-based fuzzing of the wire decoder and of the service's whole ingest path.

The service is real (``ServiceThread``: Zenoh on loopback, uvicorn, a running session on
the 20-camera lab); payloads go through ``Service._ingest_one``, the function its ingest
task calls for every Zenoh sample: decode → sensor check → clock → ``pipeline.push``.
Good messages are interleaved with bad ones and must still be taken. Every message is
accounted for (rejected by reason, accepted, or ignored), and /status shows the reasons.

``bench/reliability.py`` runs the same strategies over >= 100,000 payloads.
"""

from __future__ import annotations

import itertools
import math
import time
from collections import Counter
from typing import Any

import httpx
import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from proto import MessageError, decode
from proto.keypoints import MAX_PERSONS

TOKEN = "fuzz-token"
CAMS = ("cam_0", "cam_4", "cam_9")  # 848x480, 640x480, ...: resolutions from the lab file
SITE = "fuzz"

# ------------------------------------------------------------------ payload strategies

INT64 = st.integers(min_value=-(2**63), max_value=2**64 - 1)
JUNK_SCALAR = st.one_of(
    st.none(), st.booleans(), INT64, st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20), st.binary(max_size=40),
)
JUNK = st.recursive(JUNK_SCALAR, lambda c: st.one_of(st.lists(c, max_size=5),
                                                     st.dictionaries(st.text(max_size=8), c, max_size=5)),
                    max_leaves=12)
TOP_FIELDS = ("v", "sensor", "seq", "stamp", "size", "layout", "persons")
PERSON_FIELDS = ("kp", "bbox", "score", "cov", "track")


def person(rng: np.random.Generator, size: tuple[int, int], packed: bool = True) -> dict[str, Any]:
    w, h = size
    kp = np.column_stack([rng.uniform(0.2 * w, 0.8 * w, 17), rng.uniform(0.1 * h, 0.9 * h, 17),
                          rng.uniform(0.5, 1.0, 17)])
    return {"kp": kp.astype("<f4").tobytes() if packed else kp.tolist(),
            "bbox": [float(kp[:, 0].min()), float(kp[:, 1].min()), float(kp[:, 0].max()), float(kp[:, 1].max())],
            "score": 0.9}


def message(sensor: str, seq: int, stamp: float, size: tuple[int, int], persons: list[dict]) -> dict[str, Any]:
    return {"v": 1, "sensor": sensor, "seq": seq, "stamp": stamp, "size": list(size), "layout": "coco17",
            "persons": persons}


_RNG = np.random.default_rng(0)
HUGE_CROWD = msgpack.packb(message("cam_0", 1, 1.0, (848, 480), [person(_RNG, (848, 480))] * 10_000),
                           use_bin_type=True)  # 10,000 persons, stamp patched per use below


@st.composite
def bad_payload(draw: Any, resolutions: dict[str, tuple[int, int]]) -> tuple[str, Any]:
    """(key sensor, payload spec): a spec is bytes, or a dict whose ``stamp`` is an offset
    from the moment of sending (so that stamp checks see it relative to the clock)."""
    cam = draw(st.sampled_from(sorted(resolutions)))
    size = resolutions[cam]
    kind = draw(st.sampled_from([
        "bytes", "junk_top", "truncated", "bitflip", "drop_field", "wrong_field", "person_field",
        "nan_kp", "packed_len", "conf_range", "far_pixels", "many_persons", "huge_crowd", "unknown_sensor",
        "bad_sensor_name", "mismatch", "stamp", "seq", "size", "resolution",
    ]))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    seq = draw(st.integers(10**9, 2 * 10**9))
    base = message(cam, seq, draw(st.floats(-2.0, 0.5)), size, [person(rng, size, draw(st.booleans()))
                                                               for _ in range(draw(st.integers(0, 3)))])
    if kind == "bytes":
        return cam, draw(st.binary(max_size=300))
    if kind == "junk_top":
        return cam, msgpack.packb(draw(JUNK), use_bin_type=True)
    if kind in ("truncated", "bitflip"):
        raw = msgpack.packb({**base, "stamp": time.time()}, use_bin_type=True)
        i = draw(st.integers(0, len(raw) - 1))
        if kind == "truncated":
            return cam, raw[:i]
        return cam, raw[:i] + bytes([raw[i] ^ (1 << draw(st.integers(0, 7)))]) + raw[i + 1:]
    if kind == "drop_field":
        base.pop(draw(st.sampled_from(TOP_FIELDS)))
    elif kind == "wrong_field":
        base[draw(st.sampled_from(TOP_FIELDS))] = draw(JUNK)
    elif kind == "person_field":
        p = person(rng, size)
        f = draw(st.sampled_from(PERSON_FIELDS))
        if draw(st.booleans()) and f in p:
            p.pop(f)
        else:
            p[f] = draw(JUNK)
        base["persons"] = [p]
    elif kind == "nan_kp":
        p = person(rng, size, packed=False)
        p["kp"][draw(st.integers(0, 16))][draw(st.integers(0, 2))] = draw(st.sampled_from([math.nan, math.inf, -math.inf]))
        base["persons"] = [p]
    elif kind == "packed_len":
        base["persons"] = [{"kp": draw(st.binary(max_size=300).filter(lambda b: len(b) != 204))}]
    elif kind == "conf_range":
        p = person(rng, size, packed=False)
        p["kp"][3][2] = draw(st.one_of(st.floats(1.0001, 1e9), st.floats(-1e9, -0.0001)))
        base["persons"] = [p]
    elif kind == "far_pixels":
        p = person(rng, size, packed=False)
        p["kp"][5][0] = draw(st.floats(3.0 * size[0], 1e12))
        base["persons"] = [p]
    elif kind == "many_persons":
        base["persons"] = [person(rng, size)] * draw(st.integers(MAX_PERSONS + 1, 2 * MAX_PERSONS))
    elif kind == "huge_crowd":
        return cam, "huge_crowd"
    elif kind == "unknown_sensor":
        other = draw(st.from_regex(r"[a-z]{1,6}_[0-9]{1,3}", fullmatch=True).filter(lambda s: s not in resolutions))
        base["sensor"] = other
        return other, base
    elif kind == "bad_sensor_name":
        base["sensor"] = draw(st.one_of(st.text(min_size=1, max_size=10).filter(lambda s: not s.isalnum()),
                                        st.text(alphabet="ab", min_size=129, max_size=140), st.just("")))
    elif kind == "mismatch":
        base["sensor"] = draw(st.sampled_from([c for c in sorted(resolutions) if c != cam] + ["cam_999"]))
    elif kind == "stamp":
        base["stamp"] = draw(st.one_of(st.floats(-1e6, 1e6).map(lambda x: x * 3600 if abs(x) > 60 else x + 1e4),
                                       st.sampled_from([0, -1, 1e-9, 1e300, -1e300, math.nan, math.inf, 2**63])))
        if isinstance(base["stamp"], float) and math.isfinite(base["stamp"]) and abs(base["stamp"]) < 1e7:
            base["stamp_offset"] = True  # relative: far past / future of the clock
    elif kind == "seq":
        base["seq"] = draw(st.one_of(st.integers(-(2**63), -1), st.integers(2**62, 2**64 - 1), JUNK))
    elif kind == "size":
        base["size"] = draw(st.one_of(st.lists(INT64, max_size=4), st.tuples(st.integers(-5, 0), st.integers(-5, 5)),
                                      st.tuples(st.integers(16385, 2**40), st.integers(1, 2**40)), JUNK))
    elif kind == "resolution":  # plausible, but not the camera file's (other aspect or scaled)
        base["size"] = list(draw(st.sampled_from([(1920, 1080), (size[0] * 2, size[1] * 2), (320, 320), (size[1], size[0])])))
    return cam, base


def materialise(spec: Any, now: float) -> bytes:
    """Bytes of a payload spec, stamps relative to ``now``."""
    if isinstance(spec, bytes):
        return spec
    if spec == "huge_crowd":
        return HUGE_CROWD
    d = dict(spec)
    if d.pop("stamp_offset", None) or isinstance(d.get("stamp"), float) and -10 < d["stamp"] < 10:
        d["stamp"] = now + d["stamp"]
    try:
        return msgpack.packb(d, use_bin_type=True)
    except (OverflowError, ValueError, TypeError):  # a value msgpack cannot write: send junk
        return repr(d).encode()[:500]


# ------------------------------------------------------------------ decoder alone


@settings(max_examples=1500, derandomize=True, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(st.one_of(st.binary(max_size=400), st.tuples(st.just("cam_0"), JUNK).map(lambda t: msgpack.packb(t[1])),
                 bad_payload({"cam_0": (848, 480), "cam_4": (640, 480)}).map(lambda t: materialise(t[1], time.time()))))
def test_decoder_raises_only_message_errors(payload):
    try:
        msg = decode(payload)
    except MessageError as e:
        assert isinstance(e.field, str) and str(e)
        return
    # accepted: it must be a well-formed message
    assert msg.v == 1 and 0 < msg.size[0] <= 16384 and math.isfinite(msg.stamp) and msg.seq >= 0
    for p in msg.persons:
        assert p.kp.shape == (17, 3) and np.all(np.isfinite(p.kp))


# ------------------------------------------------------------------ the whole ingest path


@pytest.fixture(scope="module")
def fuzz_svc(tmp_path_factory, lab_dir):
    import yaml

    from backend.cameras import dump_extrinsics, load_extrinsics
    from backend.server import ServiceThread
    from proto.transport import free_port
    from backend.settings import ServiceSettings

    settings_ = ServiceSettings.load(
        None, http={"host": "127.0.0.1", "port": 0}, zenoh={"listen": (f"tcp/127.0.0.1:{free_port()}",)},
        state_dir=tmp_path_factory.mktemp("state"), token=TOKEN, site=SITE)
    intr = yaml.safe_load((lab_dir / "intrinsics.yaml").read_text())
    ref = load_extrinsics(lab_dir / "reference.yaml")
    body = {"intrinsics_yaml": yaml.safe_dump({c: intr[c] for c in CAMS}),
            "initial_yaml": dump_extrinsics({c: ref[c] for c in CAMS})}
    with ServiceThread(settings_) as svc:
        r = httpx.post(svc.url + "/sessions", json=body, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=30)
        assert r.status_code == 201, r.text
        svc.resolutions = {c: tuple(intr[c]["resolution"]) for c in CAMS}
        svc.good_seq = itertools.count(1)
        yield svc


def counts(service: Any) -> dict[str, Any]:
    return {"messages": service.messages, "rejected": Counter(service.rejected),
            "ignored": sum(service.ignored.values()),
            "accepted": {n: service.sensors.get(n).accepted for n in service.sensors.names()},
            "pipeline": service.active.pipeline.messages}


def run_batch(svc: Any, items: list[tuple[str, Any, bool]]) -> tuple[dict, dict, Counter]:
    """Ingest (sensor key, spec, good?) items on the service's loop; counters before/after."""
    service = svc.service
    key = "extrcal/" + SITE + "/sensors/{}/keypoints"

    def go() -> tuple[dict, dict, Counter]:
        before = counts(service)
        good = Counter()
        now = time.time()
        made: dict[int, bytes] = {}  # the same spec twice: the same bytes (an exact duplicate)
        for i, (sensor, spec, is_good) in enumerate(items):
            if is_good:
                good[sensor] += 1
            if id(spec) not in made:
                made[id(spec)] = materialise(spec, now + i * 1e-5 if is_good else now)
            service._ingest_one(key.format(sensor), made[id(spec)], time.time())
        return before, counts(service), good

    return svc.call(go)


def good_message(svc: Any, cam: str, rng: np.random.Generator) -> dict[str, Any]:
    size = svc.resolutions[cam]
    # stamp -0.05 s: the spec's stamp is an offset from the send time (made unique per item)
    return {**message(cam, next(svc.good_seq), -0.05, size, [person(rng, size) for _ in range(2)]),
            "stamp_offset": True}


def check_accounting(before: dict, after: dict, good: Counter, n: int) -> None:
    assert after["messages"] - before["messages"] == n
    rejected = sum((after["rejected"] - before["rejected"]).values())
    accepted = sum(after["accepted"].get(k, 0) - before["accepted"].get(k, 0) for k in after["accepted"])
    ignored = after["ignored"] - before["ignored"]
    assert rejected + accepted + ignored == n, (rejected, accepted, ignored, n)
    assert ignored == 0  # a session runs: nothing is set aside
    assert not [k for k in after["rejected"] if k.startswith("internal:")], after["rejected"]  # no bug hit
    for cam, k in good.items():  # the good messages around the bad ones were taken
        assert after["accepted"][cam] - before["accepted"].get(cam, 0) >= k, cam
    assert after["pipeline"] - before["pipeline"] >= sum(good.values())


@settings(max_examples=250, derandomize=True, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                 HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_ingest_path_survives_bad_payloads_and_keeps_good_ones(fuzz_svc, data):
    svc = fuzz_svc
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    bad = data.draw(st.lists(bad_payload(svc.resolutions), min_size=1, max_size=12))
    items: list[tuple[str, Any, bool]] = [(c, spec, False) for c, spec in bad]
    for _ in range(data.draw(st.integers(1, 4))):  # good ones at random places
        cam = data.draw(st.sampled_from(CAMS))
        items.insert(data.draw(st.integers(0, len(items))), (cam, good_message(svc, cam, rng), True))
    if data.draw(st.booleans()):  # an exact duplicate of a good message, and an old seq again
        dup = next(x for x in items if x[2])
        items.append((dup[0], dup[1], False))
    before, after, good = run_batch(svc, items)
    check_accounting(before, after, good, len(items))


def test_status_shows_every_rejection_by_reason(fuzz_svc):
    svc = fuzz_svc
    rng = np.random.default_rng(7)
    cam = CAMS[0]
    g = good_message(svc, cam, rng)
    items = [(cam, g, True), (cam, g, False),  # the same bytes again: a duplicate
             ("nobody_1", {**g, "sensor": "nobody_1"}, False), (cam, {**g, "sensor": CAMS[1]}, False),
             (cam, {**g, "stamp": 3600.0}, False), (cam, {**g, "stamp": -3600.0}, False), (cam, b"\xc1", False),
             (cam, {**g, "persons": [{"kp": b"123"}]}, False)]
    before, after, _ = run_batch(svc, items)
    new = after["rejected"] - before["rejected"]
    for reason in ("duplicate", "unknown_sensor", "sensor_mismatch", "stamp_in_future", "stamp_too_old", "malformed:payload",
                   "malformed:persons"):
        assert new[reason] >= 1, (reason, new)
    # /status may be the snapshot of up to half a second ago (as_of): the counters agree
    # once a status made after the last message is served
    truth = dict(svc.call(lambda: dict(svc.service.rejected)))
    deadline = time.monotonic() + 30
    while (status := httpx.get(svc.url + "/status", timeout=30).json())["messages"]["rejected"] != truth:
        assert time.monotonic() < deadline, (status["messages"]["rejected"], truth)
        time.sleep(0.05)
    per_sensor = status["sensors"][cam]["rejected"]
    assert per_sensor.get("stamp_in_future", 0) >= 1 and per_sensor.get("malformed:payload", 0) >= 1
    assert status["sensors"]["nobody_1"]["rejected"]["unknown_sensor"] >= 1
    assert status["session"]["state"] in ("waiting_for_data", "calibrating", "converged")
