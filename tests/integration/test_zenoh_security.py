"""Zenoh TLS and access control, for real: the backend runs with
deploy/zenoh/backend-tls-acl.json5 and sensors connect with deploy/zenoh/sensor-tls.json5
(their certificate paths rewritten to a CA and certificates generated here), both loaded
through ``ZenohSettings(config_file=...)`` as `extrcal serve` and the edge clients load
them, over tls/ on loopback to a running service.

- a sensor whose certificate the site CA signed connects and its messages reach /status;
  a certificate from another CA, no client certificate, no CA (the backend's certificate
  cannot be verified) and plain tcp/ do not connect, and nothing of theirs arrives;
- access control by certificate common name: a sensor cannot publish on another
  sensor's keys, and a CA-signed peer that is not a listed sensor cannot publish at all.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import time
from pathlib import Path

import httpx
import pytest
import yaml
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from backend.cameras import dump_extrinsics, load_extrinsics
from backend.server import ServiceThread
from proto.transport import free_port
from backend.settings import ServiceSettings
from edge_clients.publisher import SensorPublisher
from proto import KeypointMessage
from proto.transport import ZenohSettings, open_session

pytestmark = pytest.mark.slow
REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy" / "zenoh"
SITE = "secure"
CAMS = ("cam_0", "cam_1")
NO_CONNECT_WAIT = 3.0  # s a refused peer is given to connect (a good one takes ~0.1 s)


# ------------------------------------------------------------------ a small PKI


def _name(cn: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])


def _ca(cn: str):
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(_name(cn)).issuer_name(_name(cn)).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now - datetime.timedelta(hours=1))
            .not_valid_after(now + datetime.timedelta(days=1))
            .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                         content_commitment=False, key_encipherment=False, data_encipherment=False,
                                         key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    return key, cert


def _leaf(ca, cn: str):
    """A certificate for ``cn`` signed by ``ca``, valid for the loopback address."""
    ca_key, ca_cert = ca
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(_name(cn)).issuer_name(ca_cert.subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now - datetime.timedelta(hours=1))
            .not_valid_after(now + datetime.timedelta(days=1))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .add_extension(x509.SubjectAlternativeName([x509.DNSName("localhost"),
                                                        x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]),
                           critical=False)
            .sign(ca_key, hashes.SHA256()))
    return key, cert


def _write(d: Path, name: str, pair) -> None:
    key, cert = pair
    (d / f"{name}.key").write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                                      serialization.NoEncryption()))
    (d / f"{name}.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("pki")
    ca = _ca("extrcal test site CA")
    _write(d, "ca", ca)
    _write(d, "backend", _leaf(ca, "backend"))
    for cn in (*CAMS, "intruder"):
        _write(d, cn, _leaf(ca, cn))
    rogue = _ca("another CA")
    _write(d, "rogue-ca", rogue)
    _write(d, "rogue", _leaf(rogue, "cam_0"))  # claims to be cam_0, signed by the wrong CA
    return d


def _config(pki: Path, src: Path, out: Path, **replace: str) -> str:
    """The deploy example with its certificate paths pointing at ``pki``."""
    text = src.read_text().replace("/etc/extrcal/tls/", f"{pki}/")
    for a, b in replace.items():
        assert a in text, a
        text = text.replace(a, b)
    out.write_text(text)
    return str(out)


# ------------------------------------------------------------------ the service


@pytest.fixture(scope="module")
def secure_service(pki, tmp_path_factory, lab_dir):
    tmp = tmp_path_factory.mktemp("secure")
    endpoint = f"tls/127.0.0.1:{free_port()}"
    settings = ServiceSettings.load(
        None, http={"host": "127.0.0.1", "port": 0}, state_dir=tmp / "state", site=SITE,
        zenoh={"listen": (endpoint,), "config_file": _config(pki, DEPLOY / "backend-tls-acl.json5", tmp / "backend.json5")})
    intr = yaml.safe_load((lab_dir / "intrinsics.yaml").read_text())
    ref = {k: e for k, e in load_extrinsics(lab_dir / "reference.yaml").items() if k in CAMS}
    with ServiceThread(settings) as svc, httpx.Client(base_url=svc.url, timeout=30) as client:
        r = client.post("/sessions", json={"intrinsics_yaml": yaml.safe_dump({c: intr[c] for c in CAMS}),
                                           "initial_yaml": dump_extrinsics(ref), "stop": {"duration": 36000}})
        assert r.status_code == 201, r.text
        svc.endpoint, svc.client, svc.tmp = endpoint, client, tmp
        svc.size = {c: tuple(intr[c]["resolution"]) for c in CAMS}
        yield svc


def _sensor_config(svc, pki: Path, name: str, **replace: str) -> ZenohSettings:
    path = _config(pki, DEPLOY / "sensor-tls.json5", svc.tmp / f"sensor-{name}.json5", **replace)
    return ZenohSettings(config_file=path, connect=(svc.endpoint,))


def _received(svc) -> dict[str, int]:
    sensors = svc.client.get("/status").json()["sensors"]
    rows = sensors.values() if isinstance(sensors, dict) else sensors
    return {r["name"]: r["messages"] for r in rows}


def _wait_for(svc, pred, timeout: float, what: str) -> dict[str, int]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        got = _received(svc)
        if pred(got):
            return got
        time.sleep(0.05)
    raise AssertionError(f"{what}: {got}")


_seq = iter(range(1, 10**9))


def _msg(svc, sensor: str, size_of: str | None = None) -> KeypointMessage:
    return KeypointMessage(sensor=sensor, seq=next(_seq), stamp=time.time(), size=svc.size[size_of or sensor])


def _connected_within(session, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if list(session.info.peers_zid()):
            return True
        time.sleep(0.05)
    return False


# ------------------------------------------------------------------ tests


def test_ca_signed_sensor_publishes_over_tls(secure_service, pki):
    svc = secure_service
    before = _received(svc).get("cam_0", 0)
    session = open_session(_sensor_config(svc, pki, "cam_0"))
    try:
        assert _connected_within(session, 30), "the CA-signed sensor did not connect over TLS"
        with SensorPublisher(session, SITE, block=True) as pub:
            assert pub.wait_matched(["cam_0"], timeout=30), "the backend's subscriber never reached the sensor"
            for _ in range(10):
                pub.publish(_msg(svc, "cam_0"))
            _wait_for(svc, lambda got: got.get("cam_0", 0) >= before + 10, 30, "cam_0's messages did not arrive")
    finally:
        session.close()


@pytest.mark.parametrize("case", ["certificate from another CA", "no client certificate", "no CA (cannot verify the backend)",
                                  "plain tcp"])
def test_peers_without_the_site_pki_cannot_connect(secure_service, pki, case):
    svc = secure_service
    if case == "certificate from another CA":
        settings = _sensor_config(svc, pki, "rogue", **{"cam_0.pem": "rogue.pem", "cam_0.key": "rogue.key"})
    elif case == "no client certificate":
        settings = _sensor_config(svc, pki, "nocert", **{
            'connect_certificate: "': '// connect_certificate: "', 'connect_private_key: "': '// connect_private_key: "',
            "enable_mtls: true": "enable_mtls: false"})  # the client offers none: the backend must refuse it
    elif case == "no CA (cannot verify the backend)":
        settings = _sensor_config(svc, pki, "noca", **{'root_ca_certificate: "': '// root_ca_certificate: "'})
    else:  # the TLS port spoken to in plain TCP
        settings = ZenohSettings(connect=(svc.endpoint.replace("tls/", "tcp/"),))
    before = _received(svc)
    session = open_session(settings)
    try:
        assert not _connected_within(session, NO_CONNECT_WAIT), f"{case}: connected"
        pub = session.declare_publisher(f"extrcal/{SITE}/sensors/cam_0/keypoints")
        assert not pub.matching_status.matching
        pub.put(b"not even a message")
        pub.undeclare()
    finally:
        session.close()
    assert _received(svc).get("cam_0", 0) == before.get("cam_0", 0)


def test_acl_only_listed_sensors_publish_and_only_on_their_own_keys(secure_service, pki):
    svc = secure_service
    before = _received(svc)
    # a CA-signed peer whose common name is not a listed sensor: it connects (TLS is fine)
    # but the backend declares nothing to it and takes nothing from it
    intruder = open_session(_sensor_config(svc, pki, "intruder", **{"cam_0.pem": "intruder.pem",
                                                                     "cam_0.key": "intruder.key"}))
    cam0 = open_session(_sensor_config(svc, pki, "cam_0b"))
    try:
        assert _connected_within(intruder, 30), "the intruder's TLS link should be accepted (only the ACL refuses it)"
        assert _connected_within(cam0, 30)
        with SensorPublisher(intruder, SITE, block=True) as bad, SensorPublisher(cam0, SITE, block=True) as good:
            assert not bad.wait_matched(["intruder", "cam_0", "cam_1"], timeout=NO_CONNECT_WAIT), \
                "the ACL let the backend's subscriber declaration through to an unlisted peer"
            for s in ("intruder", "cam_0", "cam_1"):
                bad.publish(_msg(svc, s, size_of="cam_0" if s == "intruder" else s))
            assert good.wait_matched(["cam_0"], timeout=30)
            good.declare("cam_1")
            # cam_0 impersonating cam_1, then a message of its own on the same link (in
            # order): once that one is in, the denied one would have been before it
            for _ in range(3):
                good.publish(_msg(svc, "cam_1"))
            good.publish(_msg(svc, "cam_0"))
            got = _wait_for(svc, lambda got: got.get("cam_0", 0) >= before.get("cam_0", 0) + 1, 30,
                            "cam_0's own message did not arrive")
        assert got.get("cam_0", 0) == before.get("cam_0", 0) + 1  # not the intruder's copy
        assert got.get("cam_1", 0) == before.get("cam_1", 0), "cam_0 published as cam_1"
        assert got.get("intruder", 0) == 0, "an unlisted peer published"
        status = svc.client.get("/status").json()
        assert "unknown_sensor" not in json.dumps(status["messages"]["rejected"])  # stopped before the service
    finally:
        intruder.close()
        cam0.close()
