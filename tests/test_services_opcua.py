"""The OPC UA server of ``virtualaxis serve --opcua`` (docs/opcua.md), through real parts: serve in a child process
(udp_multicast, hop_limit 0), a ``canopen`` master here moving the drive (LockstepMaster), an asyncua client in a
third process (tests/opcua_client.py) browsing, subscribing, writing and calling methods."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
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
    assert r["inject_no_period"] == "BadInvalidArgument"
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


# ------------------------------------------------------------------------------ the server's process
def _listener_pid(port: int) -> int | None:
    """The process listening on TCP ``port`` (from /proc/net/tcp* and the processes' socket descriptors)."""
    inodes = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with open(table) as f:
            for line in f.readlines()[1:]:
                parts = line.split()
                if parts[3] == "0A" and int(parts[1].rsplit(":", 1)[1], 16) == port:  # 0A: LISTEN
                    inodes.add(f"socket:[{parts[9]}]")
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            if any(os.readlink(f"/proc/{pid}/fd/{fd}") in inodes for fd in os.listdir(f"/proc/{pid}/fd")):
                return int(pid)
        except OSError:
            continue
    return None


def _stat(pid: int) -> list[str]:
    with open(f"/proc/{pid}/stat") as f:
        return f.read().rsplit(")", 1)[1].split()


def _cpu_s(pid: int) -> float:
    """User + system CPU time of process ``pid`` (all its threads) [s]."""
    fields = _stat(pid)
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _alive(pid: int) -> bool:
    try:
        return _stat(pid)[0] != "Z"
    except OSError:
        return False


def test_server_is_a_child_process_its_clients_cost_serve_little_and_its_end_leaves_canopen_served(tmp_path):
    """The OPC UA server listens in a child process of serve; a client reading back to back costs that process
    the CPU, not serve's; when the server process is killed, serve says so once and keeps serving CANopen."""
    Client = pytest.importorskip("opcua").Client  # noqa: N806 - the class

    port = free_port()
    stats = tmp_path / "stats.json"
    with served("--lockstep", "--opcua", f"127.0.0.1:{port}", "--json", str(stats)) as srv:
        _opcua_line(srv)
        server = _listener_pid(port)
        assert server is not None and server != srv.proc.pid, (server, srv.proc.pid)
        assert int(_stat(server)[1]) == srv.proc.pid  # its parent is serve
        c = Client(f"opc.tcp://127.0.0.1:{port}/virtualaxis", timeout=30)
        c.connect()
        try:
            idx = c.get_namespace_index("urn:virtualaxis:opcua")
            axis = c.get_objects_node().get_child(f"{idx}:VirtualAxis").get_children()[0]
            position = axis.get_child([f"{idx}:ActualValues", f"{idx}:Position"])
            t0, serve0 = time.monotonic(), _cpu_s(srv.proc.pid)  # serve's own CPU rate with nobody reading
            time.sleep(2.0)
            t1, serve1, server1 = time.monotonic(), _cpu_s(srv.proc.pid), _cpu_s(server)
            values = {position.get_value() for _ in range(800)}
            t2, serve2, server2 = time.monotonic(), _cpu_s(srv.proc.pid), _cpu_s(server)
        finally:
            c.disconnect()
        assert len(values) == 1  # (lockstep, no SYNC: the drive stands still)
        server_cpu_s = server2 - server1
        serve_extra_cpu_s = (serve2 - serve1) - (serve1 - serve0) / (t1 - t0) * (t2 - t1)
        assert server_cpu_s >= 0.1, server_cpu_s  # the reads were answered there
        assert serve_extra_cpu_s < server_cpu_s / 3, (serve2 - serve1, serve1 - serve0, t1 - t0, t2 - t1,
                                                      server_cpu_s)

        os.kill(server, 9)
        net = connect(srv.spec)
        try:
            with LockstepMaster(net, 1, mode="csp") as m:
                x0 = m.position_m(1)
                trace = m.run(np.full(50, x0 + 1e-4))
        finally:
            net.disconnect()
        assert abs(float(trace.position_m[-1, 0]) - (x0 + 1e-4)) < 5e-5
    assert srv.returncode == 0, srv.stderr[-3000:]
    warnings = [ln for ln in srv.stderr.splitlines() if "OPC UA server process ended" in ln]
    assert len(warnings) == 1 and warnings[0].startswith("warning: --opcua:"), srv.stderr[-3000:]
    assert "Traceback" not in srv.stderr, srv.stderr[-3000:]
    st = json.loads(stats.read_text())["opcua"]
    assert st["server_process"] == "ended (exit code -9)" and st["server_pid"] == server, st


def test_independent_client_browse_units_subscription_fault_event_and_no_orphan():
    """python-opcua (not asyncua) against the server: the tree, a value with its EUInformation and EURange, data
    changes while a canopen master in another process moves the drive, a fault event; serve killed with SIGKILL
    takes its server process with it."""
    pytest.importorskip("opcua")
    port = free_port()
    with served("--lockstep", "--opcua", f"127.0.0.1:{port}", "--allow-fault-injection") as srv:
        _opcua_line(srv)
        client = subprocess.Popen([sys.executable, str(Path(__file__).with_name("opcua_legacy_client.py")),
                                   f"opc.tcp://127.0.0.1:{port}/virtualaxis"], stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
        assert client.stdout.readline().strip() == "subscribed", client.stderr.read() if client.poll() else ""
        net = connect(srv.spec)
        try:
            with LockstepMaster(net, 1, mode="csp") as m:
                x0 = m.position_m(1)
                ramp = x0 + np.clip(0.02 * (np.arange(300) * 0.001 - 0.02), 0.0, None)
                trace = m.run(np.concatenate([ramp, np.full(50, ramp[-1])]))
                x_end = float(trace.position_m[-1, 0])
        finally:
            net.disconnect()
        client.stdin.write("moved\n")
        client.stdin.flush()
        r = _result(client)
        server = _listener_pid(port)
        assert server is not None and server != srv.proc.pid
        srv.proc.kill()
        srv.stop()
        deadline = time.monotonic() + 10.0
        while _alive(server) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _alive(server), "the OPC UA server process outlived serve"

    assert len(r["axes"]) == 1
    assert set(r["tree"]) >= {"State", "ActualValues", "Faults", "Parameters", "Methods"}, r["tree"]
    assert r["tree"]["ActualValues"][0] == "Position"
    p = r["position"]
    assert (p["unit_id"], p["display"], p["type_definition"]) == (MTR, "m", ANALOG_ITEM_TYPE), p
    assert p["namespace"] == "http://www.opcfoundation.org/UA/units/un/cefact"
    assert p["range"][0] < p["value"] < p["range"][1]
    moving = {v for v in r["changes"] if x0 + 1e-6 < v < x_end - 1e-6}
    assert len(moving) >= 3, r["changes"]
    assert abs(r["changes"][-1] - x_end) <= 2e-6, (r["changes"][-1], x_end)
    assert r["inject_active"] == ["encoder_loss"]
    faults = [e for e in r["events"] if e["kind"] == "fault"]
    assert faults and faults[0]["emcy"] == 0x7305 and faults[0]["injected"] is True, r["events"]
    assert "0x7305" in faults[0]["message"] and faults[0]["severity"] >= 700
    assert r["fault_codes"][0] == 0x7305
