"""MQTT side channel: a real broker (fixture: mosquitto, or amqtt where mosquitto is absent), a real paho
subscriber, the drive served in real time.

Every message received is validated against its JSON Schema in docs/schemas/. Checked: topics, retained
state / birth / will, telemetry rate and batch size, fault events, the broker absent at start and killed and
restarted mid-move (nothing lost beyond the documented buffer, counters exact), credentials handling.
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import jsonschema
import paho.mqtt.client as mqtt
import pytest
from served_drive import children
from services_fixtures import ON_BOTH_BROKERS, Mosquitto, free_port, mosquitto, readable_dir  # noqa: F401 (fixture)
from test_drive_rig import seed_config, seed_discrete

from virtualaxis.runtime import AxisNode, Runtime, open_bus
from virtualaxis.services.mqtt import (
    MqttService,
    MqttSettingsError,
    load_credentials,
    parse_mqtt_url,
)

pytestmark = pytest.mark.exclusive  # timing-sensitive: background jobs stopped meanwhile

ROOT = Path(__file__).resolve().parents[1]
# topic under virtualaxis/<machine>/<axis>/ -> its schema file in docs/schemas/
SCHEMA_FILES = {"status": "status", "state": "state", "telemetry": "telemetry", "faults": "faults",
                "fault/result": "fault-result", "fault/set": "fault-set"}
SCHEMAS = {
    leaf: jsonschema.Draft202012Validator(json.loads((ROOT / "docs" / "schemas" / f"{f}.schema.json").read_text()))
    for leaf, f in SCHEMA_FILES.items()
}
COMMAND_TOPICS = ("fault/set",)  # published by clients (tests send malformed ones on purpose): not validated here


class Subscriber:
    """A paho subscriber to virtualaxis/#; validates every message against its schema as it arrives."""

    def __init__(self, port: int):
        self.port = port
        self.msgs: list[tuple[float, str, bool, dict]] = []
        self.invalid: list[str] = []
        self.lock = threading.Lock()
        self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=f"test-sub-{os.getpid()}-{port}")
        self.client.on_message = self._on_message
        self.subscribed = threading.Event()
        self.client.on_connect = lambda c, u, f, rc, p: c.subscribe("virtualaxis/#", qos=1)
        self.client.on_subscribe = lambda c, u, mid, rc, p: self.subscribed.set()
        self.client.reconnect_delay_set(0.01, 0.05)
        self.client.connect("127.0.0.1", port, keepalive=5)
        self.client.loop_start()
        assert self.subscribed.wait(10), "subscriber: no SUBACK"

    def resubscribe(self) -> None:
        """After a broker restart: reconnect now and wait for the subscription."""
        self.subscribed.clear()
        self.client.reconnect()
        assert self.subscribed.wait(10), "subscriber: no SUBACK after reconnect"

    def samples(self) -> int:
        return sum(len(m["samples"]) for m in self.of("telemetry"))

    def _on_message(self, client, userdata, m):
        leaf = m.topic.split("/", 3)[-1]  # virtualaxis/<machine>/<axis>/<leaf>
        if leaf in COMMAND_TOPICS:
            payload = {"raw": bytes(m.payload)}
        else:
            try:
                payload = json.loads(m.payload)
                SCHEMAS[leaf].validate(payload)
            except (ValueError, KeyError, jsonschema.ValidationError) as exc:
                self.invalid.append(f"{m.topic}: {exc}")
                payload = {}
        with self.lock:
            self.msgs.append((time.monotonic(), m.topic, bool(m.retain), payload))

    def of(self, leaf: str) -> list[dict]:
        with self.lock:
            return [p for _, t, _, p in self.msgs if t.endswith("/" + leaf)]

    def wait(self, predicate, timeout: float = 10.0):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            v = predicate()
            if v:
                return v
            time.sleep(0.01)
        raise AssertionError(f"condition not reached; telemetry samples received {self.samples()}; topics seen: "
                             + str(sorted({t for _, t, _, _ in self.msgs})))

    def close(self):
        self.client.loop_stop()
        self.client.disconnect()


class ServedAxis:
    """One drive served in real time on a virtual bus (runtime thread), moving in profile velocity mode."""

    def __init__(self, name: str = "X", node_id: int = 3):
        self.bus = open_bus(f"virtual:va-svc-{os.getpid()}-{time.monotonic_ns()}")
        self.axis = AxisNode(self.bus, node_id, seed_config(), name=name, discrete=seed_discrete())
        self.runtime = Runtime(self.bus, [self.axis]).start()
        self.drive = self.axis.drive

    def move(self, v_m_s: float) -> None:
        d = self.drive
        d.set_parameter("mode_of_operation", 3)
        for cw in (0x06, 0x07, 0x0F):
            d.set_controlword(cw)
            time.sleep(0.005)
        d.write_object(0x60FF, 0, int(v_m_s * 1e6))

    def close(self):
        self.runtime.stop()
        self.bus.shutdown()


def settings(url: str, **kw):
    st = parse_mqtt_url(url, "rig1")
    st.backoff_min_s = 0.1
    st.backoff_max_s = 1.0
    for k, v in kw.items():
        setattr(st, k, v)
    return st


@pytest.mark.mqtt_broker
@ON_BOTH_BROKERS
def test_topics_schema_rate_batches_and_fault_events(mosquitto):  # noqa: F811
    sub = Subscriber(mosquitto.port)
    ax = ServedAxis()
    svc = MqttService(settings(mosquitto.url), [(ax.axis.name, 3, ax.drive, lambda: "OPERATIONAL")]).start()
    try:
        ax.move(0.02)
        # steady state: the backlog of the publisher process' start-up is out (a loaded machine may start it
        # slowly, and the first batches then leave back to back) and through the broker: the subscriber has
        # all but the last two batches of what was sampled
        sub.wait(lambda: len(sub.of("telemetry")) >= 5 and len(svc.channels[0].buffer) < 10
                 and svc.channels[0].buffer.taken - sub.samples() < 25)
        t0 = time.monotonic()
        n0, taken0 = len(sub.of("telemetry")), svc.channels[0].buffer.taken
        time.sleep(2.0)
        n1, taken1 = len(sub.of("telemetry")), svc.channels[0].buffer.taken
        wall = time.monotonic() - t0
        ax.drive.inject_fault(0x4210, 42)
        sub.wait(lambda: any(f["event"] == "fault" for f in sub.of("faults")))
        sub.wait(lambda: ax.drive.state.cia402_state == "FAULT")  # fault reaction (braking) finished
        ax.drive.inject_fault(0x3220, 7)  # a second fault: one reset clears both, one event each
        sub.wait(lambda: sum(f["event"] == "fault" for f in sub.of("faults")) == 2)
        ax.drive.clear_fault()
        sub.wait(lambda: {f["emcy_code"] for f in sub.of("faults") if f["event"] == "fault_cleared"}
                 == {"0x4210", "0x3220"})
    finally:
        svc.stop()
        ax.close()
    sub.wait(lambda: sub.of("status") and sub.of("status")[-1]["status"] == "offline")
    sub.close()
    assert not sub.invalid, sub.invalid[:3]
    topics = {t for _, t, _, _ in sub.msgs}
    assert topics == {f"virtualaxis/rig1/X/{leaf}" for leaf in ("status", "state", "telemetry", "faults")}
    tel = sub.of("telemetry")
    # 100 Hz sampled (wall clock) in batches of 10 = 10 messages per second. The messages received in the
    # window are checked loosely (a loaded machine may still be draining a start-up backlog through it, seen:
    # 14.5 messages/s); the sampling rate itself tightly, from the sampler's own count.
    assert (taken1 - taken0) / wall == pytest.approx(100.0, rel=0.1)
    assert 0.85 * 10.0 <= (n1 - n0) / wall <= 2.0 * 10.0
    assert all(len(m["samples"]) == 10 for m in tel[:-1])
    samples = [s for m in tel for s in m["samples"]]
    seqs = [s["seq"] for s in samples]
    assert seqs == list(range(len(seqs)))  # nothing lost, no duplicates, in order
    dts = sorted(b["t_s"] - a["t_s"] for a, b in zip(samples[:-1], samples[1:], strict=True))
    assert dts[len(dts) // 2] == pytest.approx(0.010, abs=0.0015)  # 100 Hz in drive time (real-time pacing)
    # steady travel: the samples published before the fault was injected (the fault reaction brakes through
    # 1100 mm/min, and a braking sample may fall into the last 20 above 1100 mm/min)
    moving = [s for m in tel[:n1] for s in m["samples"] if s["velocity_mm_min"] > 1100]
    assert moving and all(abs(s["velocity_mm_min"] - 1200) < 60 for s in moving[-20:])
    assert abs(moving[-1]["speed_rpm"] - 1200 / 16.0) < 5  # 16 mm lead
    ev = [f for f in sub.of("faults") if f["event"] == "fault"][0]
    assert ev["emcy_code"] == "0x4210" and ev["fault_number"] == "F30004" and ev["fault_value"] == 42
    states = sub.of("state")
    assert any(s["cia402_state"] == "FAULT" and s["active_faults"] for s in states)
    # one state message per drive event: never the same drive state twice in a row (an event's state was
    # once published again at once as "the current state"; the last message is the one at stop)
    same = [(a["time_s"], a["cia402_state"]) for a, b in zip(states[:-2], states[1:-1], strict=True)
            if a["time_s"] == b["time_s"] and a["cia402_state"] == b["cia402_state"]]
    assert not same, same
    assert sum(1 for a, b in zip(states[:-1], states[1:], strict=True) if a["cia402_state"] != b["cia402_state"]) >= 2
    last = states[-1]["telemetry"]
    assert last["samples_taken"] == last["samples_published"] + last["samples_dropped"] + last["samples_buffered"]
    assert last["samples_published"] == len(samples) and last["samples_dropped"] == 0
    with sub.lock:
        retained = {t.rsplit("/", 1)[-1]: r for _, t, r, _ in sub.msgs}
    assert retained["telemetry"] is False and retained["faults"] is False
    # a late subscriber gets the retained state and the retained offline status
    late = Subscriber(mosquitto.port)
    late.wait(lambda: late.of("state") and late.of("status"))
    assert late.of("status")[-1]["status"] == "offline"
    late.close()


@pytest.mark.mqtt_broker
def test_broker_absent_at_start_then_killed_and_restarted_mid_move(mosquitto):  # noqa: F811
    """Buffer 60 samples (0.6 s): the outage drops exactly the oldest samples beyond it, counted; all others
    arrive once, in order."""
    port = mosquitto.port
    mosquitto.stop()  # absent at start
    ax = ServedAxis()
    # (reconnect backoff 0.1 s doubling to 4 s: the broker is started, and the test's subscriber is on it, in the
    # >= 1.6 s between two attempts, however busy the host)
    st = settings(f"mqtt://127.0.0.1:{port}", buffer_samples=60, backoff_max_s=4.0)
    svc = MqttService(st, [(ax.axis.name, 3, ax.drive, None)]).start()
    ch = svc.channels[0]
    try:
        ax.move(0.01)
        time.sleep(1.0)
        assert ch.connects == 0 and ch.buffer.dropped > 0  # the drive ran on, samples dropped and counted
        cycles = ax.drive.counters["cycles"]
        assert cycles > 900
        # the subscriber must be there before the publisher reconnects: start the broker right after a failed
        # attempt (after the 5th failure the next attempt is >= 1.6 s away)
        attempts = ch.connect_attempts
        end = time.monotonic() + 10
        while ch.connect_attempts < max(attempts + 1, 5) and time.monotonic() < end:
            time.sleep(0.002)
        mosquitto.start()
        sub = Subscriber(port)
        assert ch.connects == 0, "the publisher connected before the test's subscriber: test timing invalid"
        sub.wait(lambda: ch.connects == 1 and len(sub.of("telemetry")) >= 3)
        # kill the broker when nothing is in flight: every published sample has arrived and the next batch is
        # >= 50 ms away (QoS 0 has no delivery receipt: a batch written into the socket in the instant of an
        # unannounced crash would be lost without a trace; docs/side-channels.md)
        sub.wait(lambda: sub.samples() == ch.buffer.published and len(ch.buffer) <= 5)
        mosquitto.stop(kill=True)
        time.sleep(1.5)  # 150 samples taken meanwhile: 60 kept, the rest dropped
        attempts = ch.connect_attempts
        sub.wait(lambda: ch.connect_attempts > attempts + 1, timeout=15)  # a retry failed: next one >= 1.6 s away
        mosquitto.start()
        sub.resubscribe()
        assert ch.connects == 1, "the publisher reconnected before the test's subscriber: test timing invalid"
        sub.wait(lambda: ch.connects == 2, timeout=10)
        time.sleep(0.5)
    finally:
        svc.stop()
        ax.close()
    sub.wait(lambda: sub.of("status") and sub.of("status")[-1]["status"] == "offline")
    sub.close()
    assert not sub.invalid, sub.invalid[:3]
    c = ch.buffer.counters()
    assert c["samples_buffered"] == 0
    assert c["samples_taken"] == c["samples_published"] + c["samples_dropped"]
    tel = sub.of("telemetry")
    seqs = [s["seq"] for m in tel for s in m["samples"]]
    assert len(seqs) == len(set(seqs)) and seqs == sorted(seqs)  # no duplicates, in order
    assert len(seqs) == c["samples_published"]  # every published sample arrived
    missing = sorted(set(range(c["samples_taken"])) - set(seqs))
    assert len(missing) == c["samples_dropped"]  # exactly the counted ones are missing
    # two gaps: before the first connect and during the outage, each = taken - buffer capacity
    gaps = [[missing[0]]]
    for m in missing[1:]:
        if m == gaps[-1][-1] + 1:
            gaps[-1].append(m)
        else:
            gaps.append([m])
    assert len(gaps) == 2 and gaps[0][0] == 0
    # the samples right after each gap were kept: the oldest were dropped, the newest 60 kept
    for g in gaps:
        assert g[-1] + 1 in seqs
    # the telemetry message's cumulative drop counter matches
    assert tel[-1]["samples_dropped"] == c["samples_dropped"]
    assert sub.of("state")[-1]["connection"]["disconnects"] == 1


@pytest.mark.mqtt_broker
@ON_BOTH_BROKERS
def test_last_will_offline_when_the_process_dies(mosquitto, tmp_path):  # noqa: F811
    """`virtualaxis serve --mqtt` in its own process, killed: the broker publishes the retained will."""
    sub = Subscriber(mosquitto.port)
    cli = [sys.executable, "-c", "import sys; from virtualaxis.cli.main import main; sys.exit(main())"]
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    port = free_port()
    proc = subprocess.Popen(
        [*cli, "serve", "--can", f"udp_multicast:239.74.163.7,port={port}", "--node-id", "5", "--machine", "cell7",
         "--mqtt", mosquitto.url, "--telemetry-rate", "50", "--telemetry-batch", "5", "--status-interval", "0",
         "--modbus", "127.0.0.1:0"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )
    try:
        sub.wait(lambda: len(sub.of("telemetry")) >= 3, timeout=60)
        online = sub.of("status")[-1]
        assert online["status"] == "online" and online["node_id"] == 5 and online["telemetry_rate_hz"] == 50
        assert all(len(m["samples"]) == 5 for m in sub.of("telemetry"))
        assert sub.of("state")[-1]["nmt_state"] == "PRE-OPERATIONAL"
        proc.kill()
        proc.wait(timeout=10)
        sub.wait(lambda: sub.of("status")[-1]["status"] == "offline", timeout=30)  # keepalive 10 s x 1.5
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    sub.close()
    assert not sub.invalid, sub.invalid[:3]
    topic = {t for _, t, _, p in sub.msgs if p.get("status") == "offline"}
    assert topic == {"virtualaxis/cell7/seed000-hust/status"}


def test_credentials_come_from_a_file_or_the_environment_never_the_command_line(tmp_path):
    with pytest.raises(MqttSettingsError, match="not accepted on the command line"):
        parse_mqtt_url("mqtt://user:secret@127.0.0.1:1883", "m")
    st = parse_mqtt_url("mqtts://broker.local", "m")
    assert st.tls and st.port == 8883
    load_credentials(st, None, env={"VIRTUALAXIS_MQTT_USERNAME": "u1", "VIRTUALAXIS_MQTT_PASSWORD": "p1"})
    assert (st.username, st.password) == ("u1", "p1")
    f = tmp_path / "cred.toml"
    f.write_text('username = "u2"\npassword = "p2"\nca_file = "/etc/ssl/ca.pem"\n')
    load_credentials(st, str(f), env={})
    assert (st.username, st.password, st.ca_file) == ("u2", "p2", "/etc/ssl/ca.pem")
    f.write_text('user = "x"\n')
    with pytest.raises(MqttSettingsError, match=r"cred.toml: user: unknown key"):
        load_credentials(st, str(f), env={})
    with pytest.raises(MqttSettingsError, match="nope.toml"):
        load_credentials(st, str(tmp_path / "nope.toml"), env={})


@pytest.mark.mqtt_broker
def test_username_and_password_against_a_broker_that_requires_them(tmp_path, capfd):
    """A broker with a password file: the right credentials (from the environment) connect, wrong ones are
    refused and retried with backoff while the drive runs on, and the refusal is said once on stderr (it was
    silent but for the --json summary), without the password."""
    broker = Mosquitto(tmp_path, users={"axis": "s3cret"})
    broker.start()
    ax = ServedAxis()
    try:
        good = settings(broker.url)
        load_credentials(good, None, env={"VIRTUALAXIS_MQTT_USERNAME": "axis", "VIRTUALAXIS_MQTT_PASSWORD": "s3cret"})
        bad = settings(broker.url, machine="rig2")
        load_credentials(bad, None, env={"VIRTUALAXIS_MQTT_USERNAME": "axis", "VIRTUALAXIS_MQTT_PASSWORD": "wrong"})
        s_good = MqttService(good, [("X", 3, ax.drive, None)]).start()
        s_bad = MqttService(bad, [("X", 3, ax.drive, None)]).start()
        end = time.monotonic() + 10
        while time.monotonic() < end and not (s_good.channels[0].connects and s_bad.channels[0].connect_attempts > 2):
            time.sleep(0.05)
        s_good.stop()
        s_bad.stop()
        assert s_good.channels[0].connects == 1
        assert s_bad.channels[0].connects == 0 and s_bad.channels[0].connect_attempts > 2
        assert s_bad.channels[0].last_error
        err = capfd.readouterr().err
        assert err.count("the broker refused axis X") == 1 and "wrong" not in err and "s3cret" not in err, err
    finally:
        ax.close()
        broker.cleanup()


@pytest.mark.mqtt_broker
def test_mqtts_with_a_private_ca(tmp_path):
    """mqtts:// against a broker's TLS listener whose certificate (SAN IP 127.0.0.1) is signed by a CA given
    as ca_file in the credentials file; without that CA the connection is refused (certificate not trusted)."""
    import shutil

    if shutil.which("openssl") is None:
        pytest.skip("the openssl command (makes the test CA and certificate) is not installed")
    d = readable_dir("va-mqtt-tls-")
    try:
        def ossl(*a):
            subprocess.run(["openssl", *a], cwd=d, check=True, capture_output=True)

        ossl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", "2",
             "-subj", "/CN=virtualaxis test CA")
        ossl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", "server.key", "-out", "server.csr",
             "-subj", "/CN=127.0.0.1")
        (d / "san.ext").write_text("subjectAltName=IP:127.0.0.1\n")
        ossl("x509", "-req", "-in", "server.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
             "-out", "server.pem", "-days", "2", "-extfile", "san.ext")
        for f in d.iterdir():
            f.chmod(0o644)
        broker = Mosquitto(tmp_path, tls=(d / "ca.pem", d / "server.pem", d / "server.key"))
        broker.start()
        ax = ServedAxis()
        try:
            cred = tmp_path / "cred.toml"
            cred.write_text(f'ca_file = "{d / "ca.pem"}"\n')
            good = settings(f"mqtts://127.0.0.1:{broker.port}")
            load_credentials(good, str(cred), env={})
            untrusted = settings(f"mqtts://127.0.0.1:{broker.port}", machine="rig3")
            s_good = MqttService(good, [("X", 3, ax.drive, None)]).start()
            s_bad = MqttService(untrusted, [("X", 3, ax.drive, None)]).start()
            end = time.monotonic() + 10
            while time.monotonic() < end and not (
                s_good.channels[0].batches_published >= 2 and s_bad.channels[0].connect_attempts >= 2
            ):
                time.sleep(0.05)
            s_good.stop()
            s_bad.stop()
            assert s_good.channels[0].connects == 1 and s_good.channels[0].batches_published >= 2
            assert s_bad.channels[0].connects == 0
            assert "certificate" in s_bad.channels[0].last_error.lower()
        finally:
            ax.close()
            broker.cleanup()
    finally:
        shutil.rmtree(d, ignore_errors=True)


def test_sample_dropped_while_its_batch_is_in_flight_counts_as_published():
    """The sampler drops the oldest samples of a full buffer while the publisher is writing a batch that holds
    them: they were delivered, so they count as published, not dropped (seen in CI under load: the subscriber
    received more samples than the counter said were published)."""
    from virtualaxis.services.mqtt import SampleBuffer

    buf = SampleBuffer(capacity=5)
    for seq in range(5):
        buf.add({"seq": seq})
    batch = buf.peek(3)  # seq 0..2 in flight
    buf.add({"seq": 5})
    buf.add({"seq": 6})  # the full buffer drops seq 0 and 1, both in flight
    assert buf.dropped == 2
    buf.commit(batch)
    c = buf.counters()
    assert c == {"samples_taken": 7, "samples_published": 3, "samples_dropped": 0, "samples_buffered": 4}
    assert [s["seq"] for s in buf.peek(10)] == [3, 4, 5, 6]
    buf.add({"seq": 7})
    buf.add({"seq": 8})  # full again: seq 3 (not in flight) is dropped and stays a drop
    assert buf.counters()["samples_dropped"] == 1


def test_a_broker_of_mqtt_3_1_1_only_is_served_in_3_1_1():
    """serve's publisher speaks MQTT 5 (retain-as-published: a retained fault/set command is seen as one and
    refused); a broker that knows only 3.1.1 answers its CONNECT with return code 1 (unacceptable protocol
    version, MQTT 3.1.1 section 3.2.2.3). The publisher then connects again at once in 3.1.1. The broker here
    is a minimal one written in the test: it refuses protocol level 5, accepts level 4 and records both."""
    import socket

    levels: list[int] = []
    srv = socket.create_server(("127.0.0.1", 0))
    srv.settimeout(0.2)
    port = srv.getsockname()[1]
    stop = threading.Event()

    def connect_level(conn) -> int:
        head = conn.recv(1)
        assert head and head[0] >> 4 == 1  # CONNECT
        length, shift = 0, 0
        while True:
            b = conn.recv(1)[0]
            length |= (b & 0x7F) << shift
            shift += 7
            if not b & 0x80:
                break
        body = b""
        while len(body) < length:
            body += conn.recv(length - len(body))
        name_len = int.from_bytes(body[:2], "big")
        assert body[2:2 + name_len] == b"MQTT"
        return body[2 + name_len]

    def broker() -> None:
        held = []
        while not stop.is_set():
            try:
                conn, _ = srv.accept()
            except TimeoutError:
                continue
            conn.settimeout(2.0)
            level = connect_level(conn)
            levels.append(level)
            if level == 5:
                conn.sendall(bytes([0x20, 0x02, 0x00, 0x01]))  # a 3.1.1 CONNACK: unacceptable protocol version
                conn.close()
            else:
                conn.sendall(bytes([0x20, 0x02, 0x00, 0x00]))  # accepted (then nothing more is answered)
                held.append(conn)
        for c in held:
            c.close()

    t = threading.Thread(target=broker, daemon=True)
    t.start()
    ax = ServedAxis()
    svc = MqttService(settings(f"mqtt://127.0.0.1:{port}"), [(ax.axis.name, 3, ax.drive, lambda: "OPERATIONAL")])
    try:
        svc.start()
        end = time.monotonic() + 15.0
        while 4 not in levels and time.monotonic() < end:
            time.sleep(0.05)
    finally:
        svc.stop()
        ax.close()
        stop.set()
        t.join(5)
        srv.close()
    assert levels[:2] == [5, 4], levels


@contextlib.contextmanager
def _fifo_for_new_threads(priority: int):
    """The threads started inside run at SCHED_FIFO ``priority`` when this process has the right (as ``serve
    --rt-priority`` sets it before its threads start); unchanged otherwise."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError):
        yield
        return
    try:
        yield
    finally:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


@contextlib.contextmanager
def _telemetry_at_1000_hz(url: str):
    """A served axis and its MQTT service at 1000 Hz (batches of 50), both started at SCHED_FIFO where the
    process may (the drive's thread too: the sampler takes the drive's lock); stopped at the end."""
    from virtualaxis.services.cycle_gate import CycleGate

    with _fifo_for_new_threads(10):
        ax = ServedAxis()
        svc = MqttService(settings(url, rate_hz=1000.0, batch_size=50),
                          [(ax.axis.name, 3, ax.drive, lambda: "OPERATIONAL")], gate=CycleGate()).start()
    try:
        yield ax, svc
    finally:
        svc.stop()
        ax.close()


def test_telemetry_at_1000_hz_is_sampled_at_1000_hz(mosquitto):  # noqa: F811
    """--telemetry-rate up to 1000 Hz (the documented maximum) is sampled at that rate, not in the next drive
    cycle's PDO gap (or its 2 ms time-out without a master). Sampled by serve's own count over 2 s (what
    reaches the broker is checked by the tests above). Where the process may, its sampler runs at SCHED_FIFO as
    under ``serve --rt-priority`` (threads inherit the policy): on a host with other work a thread of normal
    priority wakes too late for 1 ms periods (150 Hz beside four CPU-bound processes on two cores)."""
    with _telemetry_at_1000_hz(mosquitto.url) as (ax, svc):
        time.sleep(0.5)
        c0, t0 = svc.stats()[ax.axis.name]["samples_taken"], time.monotonic()
        time.sleep(2.0)
        c1, t1 = svc.stats()[ax.axis.name]["samples_taken"], time.monotonic()
    assert (c1 - c0) / (t1 - t0) > 800, (c1 - c0) / (t1 - t0)


def test_a_publisher_stopped_for_long_neither_blocks_the_sampler_nor_loses_an_event(mosquitto, monkeypatch):  # noqa: F811
    """Messages to a publisher process that stopped taking them (SIGSTOP here; a starved one in the field) wait
    in serve without blocking the sampler: the current state is forwarded every sample here (as if the publisher
    had been stopped for minutes at the usual 10 Hz), so the socket to it fills within a second; a blocking send
    then stopped the sampler for as long as the publisher. A fault raised meanwhile is published once the
    publisher runs again, and the state it publishes last is the drive's current one."""
    from virtualaxis.services import mqtt as mqtt_module

    monkeypatch.setattr(mqtt_module, "STATE_FORWARD_PERIOD_S", 0.001)  # read when the sampler starts
    sub = Subscriber(mosquitto.port)
    try:
        with _telemetry_at_1000_hz(mosquitto.url) as (ax, svc):
            with _publisher_stopped(ax, svc) as stopped:
                time.sleep(1.5)
                ax.drive.inject_fault(0x4210, 42)
                time.sleep(1.5)
                waiting = len(getattr(svc, "backlog", ()))
            sub.wait(lambda: any(f["event"] == "fault" and f["emcy_code"] == "0x4210" for f in sub.of("faults")),
                     timeout=30.0)
            sub.wait(lambda: sub.of("state") and sub.of("state")[-1]["cia402_state"] == "FAULT", timeout=30.0)
            dropped = svc.messages_dropped
    finally:
        sub.close()
    assert stopped["rate"] > 800, stopped
    assert 1 <= waiting < 10, waiting  # the fault's event and snapshot, one current state: not 3 000 states
    assert dropped == 0


@contextlib.contextmanager
def _publisher_stopped(ax, svc):
    """The publisher process of ``svc`` stopped (SIGSTOP) for the block, after 0.5 s of running; yields a dict
    that holds, after the block, the sampler's ``rate`` [samples/s] while the publisher was stopped."""
    import signal

    child = _publisher_process(os.getpid())
    time.sleep(0.5)
    out: dict = {}
    os.kill(child, signal.SIGSTOP)
    try:
        c0, t0 = svc.stats()[ax.axis.name]["samples_taken"], time.monotonic()
        yield out
        c1, t1 = svc.stats()[ax.axis.name]["samples_taken"], time.monotonic()
        out["rate"] = (c1 - c0) / (t1 - t0)
    finally:
        os.kill(child, signal.SIGCONT)


def _publisher_process(parent: int) -> int:
    """The pid of the MQTT publisher process started by ``parent``."""
    for pid in children(parent):
        try:
            if b"publisher_child" in Path(f"/proc/{pid}/cmdline").read_bytes():
                return pid
        except OSError:
            continue
    raise AssertionError("no publisher process")


def test_a_stalled_publisher_process_does_not_stall_the_sampler(mosquitto):  # noqa: F811
    """The publisher process runs below the drive, so on a busy host it can go without CPU for a while. The
    sampler in serve must keep its rate meanwhile: here the publisher process is stopped (SIGSTOP) for 2 s of
    1000 Hz telemetry. A wake sent at every sample fills the socket to the stopped process within ~0.3 s and then
    blocks the sampler; wakes to a publisher that far behind are not sent (counted), and what it missed is in the
    ring when it runs again."""
    with _telemetry_at_1000_hz(mosquitto.url) as (ax, svc):
        with _publisher_stopped(ax, svc) as stopped:
            time.sleep(2.0)
        skipped = svc.wakes_skipped
        published0 = svc.stats()[ax.axis.name]["samples_published"]
        end = time.monotonic() + 30.0  # (it runs at nice 10: on a busy host it may take a while to run again)
        while svc.stats()[ax.axis.name]["samples_published"] <= published0 + 2000 and time.monotonic() < end:
            time.sleep(0.05)
        published1 = svc.stats()[ax.axis.name]["samples_published"]
    assert stopped["rate"] > 800, stopped
    assert skipped > 0
    assert published1 > published0 + 2000, "the publisher did not take up the samples of its stop after SIGCONT"
