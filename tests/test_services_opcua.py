"""The OPC UA server of ``virtualaxis serve --opcua`` (docs/opcua.md), through real parts: serve in a child process
(udp_multicast, hop_limit 0), a ``canopen`` master here moving the drive (LockstepMaster), an asyncua client in a
third process (tests/opcua_client.py) browsing, subscribing, writing and calling methods."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from served_drive import CLI, ROOT, served
from services_fixtures import free_port

from virtualaxis.master import LockstepMaster, connect

pytest.importorskip("asyncua")
pytestmark = pytest.mark.exclusive  # a lockstep master and two servers: background jobs stopped meanwhile

CLIENT = [sys.executable, str(Path(__file__).with_name("opcua_client.py"))]
MTR, MTS, AMP, NU, CEL = 5067858, 5067859, 4279632, 20053, 4408652  # UNECE codes MTR, MTS, AMP, NU, CEL
ANALOG_ITEM_TYPE = 2368


def _client(url: str, scenario: str, opts: dict | None = None) -> subprocess.Popen:
    return subprocess.Popen([*CLIENT, url, scenario, json.dumps(opts or {})], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)


def _result(proc: subprocess.Popen, timeout_s: float = 120.0) -> dict:
    out, err = proc.communicate(timeout=timeout_s)
    lines = [ln for ln in out.splitlines() if ln.startswith("result ")]
    assert lines, f"no result from the client:\n{out}\n{err}"
    res = json.loads(lines[-1][len("result "):])
    assert "error" not in res, (res["error"], err[-3000:])
    return res


def _opcua_line(srv) -> str:
    line = srv.proc.stdout.readline()
    assert line.startswith("opcua: opc.tcp://"), line
    return line


def test_browse_subscribe_write_and_fault_event_from_other_processes():
    port = free_port()
    with served("--lockstep", "--opcua", f"127.0.0.1:{port}", "--opcua-writable", "--allow-fault-injection") as srv:
        line = _opcua_line(srv)
        assert "read/write parameters, anonymous, no security" in line, line
        client = _client(f"opc.tcp://127.0.0.1:{port}/virtualaxis", "full")
        assert client.stdout.readline().strip() == "subscribed", client.stderr.read() if client.poll() else ""
        net = connect(srv.spec)
        try:
            with LockstepMaster(net, 1, mode="csp") as m:
                x0 = m.position_m(1)
                ramp = x0 + np.clip(0.02 * (np.arange(400) * 0.001 - 0.02), 0.0, None)  # 20 mm/s for 0.38 s
                trace = m.run(np.concatenate([ramp, np.full(100, ramp[-1])]))
                x_end = float(trace.position_m[-1, 0])
        finally:
            net.disconnect()
        client.stdin.write(f"moved {x_end!r}\n")
        client.stdin.flush()
        r = _result(client)
    assert srv.returncode == 0, srv.stderr[-3000:]

    # the tree
    assert len(r["axes"]) == 1
    tree = r["tree"]
    assert set(tree) >= {"State", "ActualValues", "Faults", "Parameters", "Methods"}, tree
    assert tree["ActualValues"] == ["Position", "Velocity", "FollowingError", "Current", "Torque", "MotorTemperature"]
    assert {"CiA402State", "Statusword", "ModeOfOperation", "NmtState"} <= set(tree["State"])
    assert {"FaultActive", "ErrorCode", "FaultBuffer"} <= set(tree["Faults"])
    assert {"kv_1000_per_min", "software_limit_max_m", "LastWriteResult"} <= set(tree["Parameters"])
    assert tree["Methods"] == ["InjectFault", "ClearFault"]
    # engineering units (UNECE) and ranges
    u = r["units"]
    assert {k: v["unit_id"] for k, v in u.items()} == {"Position": MTR, "Velocity": MTS, "FollowingError": MTR,
                                                       "Current": AMP, "Torque": NU, "MotorTemperature": CEL}
    assert all(v["namespace"] == "http://www.opcfoundation.org/UA/units/un/cefact" for v in u.values())
    assert all(v["type_definition"] == ANALOG_ITEM_TYPE for v in u.values())
    lo, hi = u["Position"]["range"]
    assert lo < 0 < hi and lo < x_end < hi
    assert u["Velocity"]["range"][0] == -u["Velocity"]["range"][1] < 0
    assert r["kv_range"][0] == 0.0  # the EDS's LowLimit of 0x2000

    # data changes while the master moved the drive: many distinct positions, rising, ending where the master is
    changes = r["changes"]
    moving = [v for v in changes if x0 + 1e-6 < v < x_end - 1e-6]
    assert len(set(moving)) >= 3, changes
    # (the follower may overshoot the end of the ramp by a few um and settle back: bounds, not monotony)
    assert all(x0 - 20e-6 <= v <= x_end + 200e-6 for v in changes), changes
    half = (x0 + x_end) / 2
    assert changes[0] < half and next(i for i, v in enumerate(changes) if v > half) > 0, changes
    assert abs(changes[-1] - x_end) <= 2e-6 and abs(r["position_read"] - x_end) <= 2e-6, (changes[-1], x_end)

    # refused writes: the status code of the SDO check, the value unchanged, the reason readable
    ref = r["refused"]
    expect = {"kv_negative": "BadOutOfRange", "kv_too_high": "BadOutOfRange", "kv_nan": "BadOutOfRange",
              "kv_string": "BadTypeMismatch", "kv_int": "BadTypeMismatch",
              "homing_method_unsupported": "BadOutOfRange", "position": "BadNotWritable",
              "statusword": "BadNotWritable"}
    assert {k: v["status"] for k, v in ref.items()} == expect, ref
    for label in ("kv_negative", "kv_too_high", "kv_nan", "kv_string", "kv_int"):
        assert ref[label]["after"] == r["kv_before"], (label, ref[label])
    assert "refused BadOutOfRange" in ref["kv_negative"]["last"] and "0x06090032" in ref["kv_negative"]["last"]
    assert "refused BadTypeMismatch" in ref["kv_string"]["last"]
    assert r["kv_after_refused"] == r["kv_before"]
    assert r["kv_accepted"] == "Good" and r["kv_after_accepted"] == pytest.approx(r["kv_before"] * 0.5, rel=1e-6)

    # fault injection by method, the fault as an event
    assert r["inject_unknown"] == "BadInvalidArgument"
    assert r["inject_active"] == ["encoder_loss"]
    faults = [e for e in r["events"] if e["kind"] == "fault"]
    assert len(faults) == 2, r["events"]  # from the axis object and from the Server object
    assert all(e["emcy"] == 0x7305 and e["injected"] is True and e["source"] == r["axes"][0] for e in faults), faults
    assert faults[0]["severity"] >= 700 and "0x7305" in faults[0]["message"]
    assert r["error_code"] == 0x7305 and r["fault_codes"][0] == 0x7305
    assert r["clear_int"] == "BadTypeMismatch" and r["clear_active"] in ([], None), r


def _self_signed(tmp: Path, name: str) -> tuple[str, str]:
    """A certificate / key pair (PEM) for an OPC UA application ``urn:virtualaxis:<name>``."""
    import datetime

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import rsa
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    now = datetime.datetime.now(datetime.timezone.utc)
    uri = "urn:virtualaxis:server" if name == "server" else "urn:freeopcua:client"
    cert = (x509.CertificateBuilder().subject_name(subject).issuer_name(subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now - datetime.timedelta(days=1))
            .not_valid_after(now + datetime.timedelta(days=30))
            .add_extension(x509.SubjectAlternativeName([x509.UniformResourceIdentifier(uri),
                                                        x509.DNSName("localhost")]), critical=False)
            .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=True, key_encipherment=True,
                                         data_encipherment=True, key_agreement=False, key_cert_sign=True,
                                         crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .sign(key, hashes.SHA256()))
    c, k = tmp / f"{name}-cert.pem", tmp / f"{name}-key.pem"
    c.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    k.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.TraditionalOpenSSL,
                                    serialization.NoEncryption()))
    return str(c), str(k)


def test_username_login_encrypted_channel_and_read_only_by_default(tmp_path):
    users = tmp_path / "users.toml"
    users.write_text('[users]\noperator = "s3cret-pass"\n')
    cert, key = _self_signed(tmp_path, "server")
    client_cert, client_key = _self_signed(tmp_path, "client")
    port = free_port()
    with served("--lockstep", "--opcua", f"127.0.0.1:{port}", "--opcua-users", str(users), "--opcua-cert", cert,
                "--opcua-key", key) as srv:
        line = _opcua_line(srv)
        assert "read-only, username/password, Basic256Sha256 SignAndEncrypt" in line, line
        r = _result(_client(f"opc.tcp://127.0.0.1:{port}/virtualaxis", "secure",
                            {"user": "operator", "password": "s3cret-pass", "cert": True,
                             "client_cert": client_cert, "client_key": client_key}))
    assert r["anonymous"].startswith("refused"), r
    assert r["wrong_password"].startswith("refused"), r
    assert r["right_password"] == "connected", r
    assert "Methods" not in r["folders"], r  # no --allow-fault-injection: no fault-injection methods
    assert r["write"] == "BadNotWritable" and r["kv_unchanged"], r


@pytest.mark.parametrize(("args", "needle"), [
    (["--opcua-writable"], "--opcua-writable need(s) --opcua"),
    (["--opcua", "127.0.0.1:http"], "--opcua '127.0.0.1:http': port 'http' is not a number"),
    (["--opcua", "0.0.0.0:4840"], "anonymous access is served on loopback addresses only"),
    (["--opcua", "--opcua-users", "{tmp}/missing.toml"], "--opcua-users {tmp}/missing.toml: file not found"),
    (["--opcua", "--opcua-users", "{tmp}/bad.toml"], "users.operator: the password must be a non-empty string"),
    (["--opcua", "--opcua-cert", "{tmp}/bad.toml"], "--opcua-cert and --opcua-key go together"),
    (["--opcua", "--opcua-cert", "{tmp}/bad.toml", "--opcua-key", "{tmp}/server-key.pem"],
     "--opcua-cert {tmp}/bad.toml: not a PEM or DER certificate"),
    (["--opcua", "--opcua-cert", "{tmp}/server-cert.pem", "--opcua-key", "{tmp}/client-key.pem"],
     "--opcua-key {tmp}/client-key.pem: not the private key of --opcua-cert {tmp}/server-cert.pem"),
])
def test_bad_options_one_error_line(tmp_path, args, needle):
    (tmp_path / "bad.toml").write_text("[users]\noperator = 7\n")
    _self_signed(tmp_path, "server")
    _self_signed(tmp_path, "client")
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    p = subprocess.run([*CLI, "serve", "--can", "udp_multicast:239.74.1.1,port=47999", *args], capture_output=True,
                       text=True, timeout=120, cwd=ROOT)
    assert p.returncode == 2, (p.stdout, p.stderr)
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), p.stderr
    assert needle.replace("{tmp}", str(tmp_path)) in lines[0], lines[0]


def test_without_asyncua_one_error_line_naming_the_extra(tmp_path):
    shim = tmp_path / "asyncua"
    shim.mkdir()
    (shim / "__init__.py").write_text("raise ImportError('asyncua hidden for this test')\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    p = subprocess.run([*CLI, "serve", "--can", "udp_multicast:239.74.1.1,port=47999", "--opcua"],
                       capture_output=True, text=True, timeout=120, cwd=ROOT, env=env)
    assert p.returncode == 2, (p.stdout, p.stderr)
    assert p.stderr.strip().splitlines() == [
        "error: --opcua needs the asyncua package, not installed here (pip install 'virtualaxis[opcua]')"], p.stderr
