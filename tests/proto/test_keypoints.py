"""Keypoint message v1: round trips in every form, and every kind of bad message."""

from __future__ import annotations

import copy
import json
import math

import msgpack
import numpy as np
import pytest

from proto import COCO17, N_JOINTS, KeypointMessage, MessageError, Person, decode, encode, from_dict, to_dict


def _msg(persons: int = 2, *, with_optional: bool = True) -> KeypointMessage:
    rng = np.random.default_rng(7)
    ps = []
    for i in range(persons):
        kp = np.column_stack([rng.uniform(0, 848, 17), rng.uniform(0, 480, 17), rng.uniform(0, 1, 17)])
        kp[3, 2] = 0.0  # an undetected joint
        if with_optional:
            cov = np.column_stack([rng.uniform(1, 9, 17), rng.uniform(-1, 1, 17), rng.uniform(1, 9, 17)])
            ps.append(Person(kp=kp, bbox=np.array([1.0, 2.0, 300.5, 470.25]), score=0.9 - 0.1 * i, cov=cov, track=i))
        else:
            ps.append(Person(kp=kp))
    return KeypointMessage(sensor="cam_3", seq=12, stamp=1700000000.033, size=(848, 480), persons=tuple(ps))


def _as_float32(msg: KeypointMessage) -> KeypointMessage:
    """What survives packing: kp/cov rounded to float32."""
    ps = tuple(Person(kp=p.kp.astype(np.float32).astype(np.float64), bbox=p.bbox, score=p.score,
                      cov=None if p.cov is None else p.cov.astype(np.float32).astype(np.float64), track=p.track)
               for p in msg.persons)
    return KeypointMessage(msg.sensor, msg.seq, msg.stamp, msg.size, ps, msg.layout, msg.v)


def test_coco17_layout():
    assert N_JOINTS == len(COCO17) == 17
    assert COCO17[0] == "nose" and COCO17[9] == "l_wrist" and COCO17[16] == "r_ankle"


@pytest.mark.parametrize("optional", [True, False])
def test_msgpack_packed_round_trip(optional):
    msg = _msg(with_optional=optional)
    got = decode(encode(msg, packed=True))
    assert got == _as_float32(msg)
    assert got.persons[0].kp.dtype == np.float64 and got.persons[0].kp.shape == (17, 3)


def test_msgpack_nested_lists_round_trip_is_exact():
    msg = _msg()
    raw = encode(msg, packed=False)
    d = msgpack.unpackb(raw)
    assert isinstance(d["persons"][0]["kp"], list)
    assert decode(raw) == msg


def test_packed_form_is_float32_little_endian_row_major():
    msg = _msg(1)
    d = msgpack.unpackb(encode(msg, packed=True))
    raw = d["persons"][0]["kp"]
    assert isinstance(raw, bytes) and len(raw) == 17 * 3 * 4
    arr = np.frombuffer(raw, "<f4").reshape(17, 3)
    np.testing.assert_allclose(arr, msg.persons[0].kp, rtol=1e-6)


def test_any_msgpack_library_can_publish_nested_lists():
    """A publisher that knows nothing of our code: plain maps and lists."""
    d = {"v": 1, "sensor": "cam_0", "seq": 0, "stamp": 1.7e9, "size": [640, 480],
         "persons": [{"kp": [[10, 20, 0.9]] * 17}]}
    msg = decode(msgpack.packb(d))
    assert msg.persons[0].kp[0].tolist() == [10.0, 20.0, 0.9]
    assert msg.layout == "coco17" and msg.persons[0].bbox is None


def test_json_round_trip_and_empty_persons():
    msg = _msg()
    assert from_dict(json.loads(json.dumps(to_dict(msg))), default_version=1) == msg
    empty = KeypointMessage("cam_1", 0, 1.7e9, (640, 480))
    assert from_dict(json.loads(json.dumps(to_dict(empty)))) == empty
    assert empty.keypoints().shape == (0, 17, 3)
    assert msg.keypoints().shape == (2, 17, 3)


def test_version_missing_is_1_only_in_json_lines():
    d = to_dict(_msg(1))
    del d["v"]
    assert from_dict(d, default_version=1).v == 1
    with pytest.raises(MessageError) as e:
        decode(msgpack.packb(d, use_bin_type=True))
    assert e.value.field == "v" and "missing" in e.value.reason


def _base() -> dict:
    return to_dict(_msg(3), packed=False)


def _set(d: dict, path: tuple, value) -> dict:
    d = copy.deepcopy(d)
    cur = d
    for k in path[:-1]:
        cur = cur[k]
    if value is _DELETE:
        del cur[path[-1]]
    else:
        cur[path[-1]] = value
    return d


_DELETE = object()

BAD = [
    # (path, value, field, reason fragment)
    (("v",), 2, "v", "unsupported version 2"),
    (("v",), "1", "v", "expected an integer, got str"),
    (("sensor",), _DELETE, "sensor", "missing"),
    (("sensor",), "", "sensor", "non-empty string"),
    (("sensor",), 7, "sensor", "non-empty string"),
    (("sensor",), "cam/3", "sensor", "only letters"),
    (("sensor",), "c" * 129, "sensor", "at most 128"),
    (("seq",), _DELETE, "seq", "missing"),
    (("seq",), -1, "seq", "must be >= 0"),
    (("seq",), 1.5, "seq", "expected an integer, got float"),
    (("seq",), True, "seq", "expected an integer, got bool"),
    (("stamp",), _DELETE, "stamp", "missing"),
    (("stamp",), "now", "stamp", "expected a number, got str"),
    (("stamp",), float("nan"), "stamp", "finite"),
    (("stamp",), float("inf"), "stamp", "finite"),
    (("stamp",), 0, "stamp", "seconds since the Unix epoch"),
    (("stamp",), -5.0, "stamp", "seconds since the Unix epoch"),
    (("stamp",), 1.7e12, "stamp", "(milliseconds?)"),  # a detector stamping in other units
    (("stamp",), 1.7e15, "stamp", "(microseconds?)"),
    (("stamp",), 1_700_000_000_000_000_000, "stamp", "(nanoseconds?)"),
    (("size",), _DELETE, "size", "missing"),
    (("size",), [848], "size", "expected [width, height]"),
    (("size",), [848, 0], "size", "not a plausible image size"),
    (("size",), [100000, 480], "size", "not a plausible image size"),
    (("size",), [848.0, 480], "size[0]", "expected an integer, got float"),
    (("layout",), "body25", "layout", "unknown layout 'body25'"),
    (("persons",), _DELETE, "persons", "missing"),
    (("persons",), {"kp": []}, "persons", "expected a list, got dict"),
    (("persons",), [{"kp": [[0, 0, 0]] * 17}] * 257, "persons", "257 persons, at most 256"),
    (("persons", 1), "person", "persons[1]", "expected a map, got str"),
    (("persons", 2, "kp"), _DELETE, "persons[2].kp", "missing"),
    (("persons", 2, "kp"), [[1.0, 2.0, 0.5]] * 16, "persons[2].kp", "expected 17 rows of 3, got 16"),
    (("persons", 2, "kp"), [[1.0, 2.0, 0.5]] * 18, "persons[2].kp", "expected 17 rows of 3, got 18"),
    (("persons", 0, "kp", 4), [1.0, 2.0], "persons[0].kp[4]", "expected 3 numbers, got 2"),
    (("persons", 0, "kp", 4), 5, "persons[0].kp[4]", "expected 3 numbers, got int"),
    (("persons", 0, "kp", 4, 1), "x", "persons[0].kp[4][1]", "expected a number, got str"),
    (("persons", 0, "kp", 4, 1), None, "persons[0].kp[4][1]", "expected a number, got NoneType"),
    (("persons", 0, "kp", 5, 0), float("nan"), "persons[0].kp[5]", "NaN or infinite"),
    (("persons", 0, "kp", 5, 2), 1.5, "persons[0].kp[5]", "confidence 1.5 outside [0, 1]"),
    (("persons", 0, "kp", 5, 2), -0.1, "persons[0].kp[5]", "outside [0, 1]"),
    (("persons", 1, "kp"), "abc", "persons[1].kp", "expected a list or packed bytes, got str"),
    (("persons", 1, "kp"), b"\0" * 200, "persons[1].kp", "packed float32 needs 204 bytes (17x3), got 200"),
    (("persons", 0, "kp", 6), [1e6, 10.0, 0.9], "persons[0].kp", "far outside the 848x480 image"),
    (("persons", 0, "bbox"), [1, 2, 3], "persons[0].bbox", "expected [x0, y0, x1, y1]"),
    (("persons", 0, "bbox"), [1, 2, 3, "x"], "persons[0].bbox[3]", "expected a number"),
    (("persons", 0, "score"), "high", "persons[0].score", "expected a number, got str"),
    (("persons", 0, "score"), float("inf"), "persons[0].score", "finite"),
    (("persons", 0, "cov"), [[1, 0, 1]] * 3, "persons[0].cov", "expected 17 rows of 3, got 3"),
    (("persons", 0, "cov", 2), [-1.0, 0.0, 1.0], "persons[0].cov", "negative variance"),
    (("persons", 0, "track"), 1.5, "persons[0].track", "expected an integer, got float"),
]


@pytest.mark.parametrize("path,value,field,reason", BAD, ids=[f"{b[2]}:{b[3]}" for b in BAD])
def test_bad_message_names_field_and_reason(path, value, field, reason):
    d = _set(_base(), path, value)
    with pytest.raises(MessageError) as e:
        from_dict(d)
    assert e.value.field == field
    assert reason in e.value.reason
    assert str(e.value).startswith(f"{field}: ")


def test_not_a_map():
    with pytest.raises(MessageError, match="expected a map at the top level, got list"):
        from_dict([1, 2])


@pytest.mark.parametrize("payload", [b"", b"\xc1", b"\x93\x01\x02", b"garbage that is not msgpack \xff\xfe"])
def test_decode_garbage_is_a_message_error(payload):
    with pytest.raises(MessageError):
        decode(payload)


def test_packed_nan_is_rejected():
    d = _base()
    kp = np.array(d["persons"][0]["kp"], "<f4")
    kp[2, 0] = np.nan
    d["persons"][0]["kp"] = kp.tobytes()
    with pytest.raises(MessageError) as e:
        decode(msgpack.packb(d, use_bin_type=True))
    assert e.value.field == "persons[0].kp[2]" and "NaN" in e.value.reason


def test_extra_keys_are_ignored_and_optional_null():
    d = _base()
    d["extra"] = {"anything": 1}
    d["persons"][0]["bbox"] = None
    d["persons"][0]["score"] = None
    msg = from_dict(d)
    assert msg.persons[0].bbox is None and msg.persons[0].score is None


def test_pixels_slightly_outside_the_image_are_accepted():
    d = _set(_base(), ("persons", 0, "kp", 6), [-20.0, 485.0, 0.4])
    assert from_dict(d).persons[0].kp[6, 0] == -20.0
    # an undetected joint may hold anything finite
    d = _set(_base(), ("persons", 0, "kp", 6), [1e7, 1e7, 0.0])
    assert from_dict(d).persons[0].kp[6, 2] == 0.0


def test_stamp_precision_survives_json_and_msgpack():
    msg = KeypointMessage("cam_0", 1, 1700000000.123456, (848, 480))
    assert decode(encode(msg)).stamp == msg.stamp
    assert from_dict(json.loads(json.dumps(to_dict(msg)))).stamp == msg.stamp
    assert math.isclose(msg.stamp, 1700000000.123456, abs_tol=1e-6)
