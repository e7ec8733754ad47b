"""Sparkplug B telemetry (`virtualaxis serve --mqtt URL --sparkplug GROUP`) as a primary host sees it: serve in a
subprocess against a real broker (mosquitto, or amqtt where it is absent), a paho subscriber in this process
decoding every payload with the tests' own wire-format decoder (tests/sparkplug_decoder.py, no protobuf), a
CANopen master enabling the drive over udp_multicast. Checked: the topic tree, birth metrics (names, aliases,
datatypes, units), alias-only DDATA, seq 0..255 in order from each NBIRTH, the NDEATH will's bdSeq after kill -9,
rebirth on NCMD, DCMD fault commands, bad commands refused and answered without losing a message."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
import time
from pathlib import Path

import canopen
import paho.mqtt.client as mqtt
import pytest
from served_drive import CLI, ROOT, served
from services_fixtures import mosquitto  # noqa: F401 (fixture)
from sparkplug_decoder import decode, encode_command

from virtualaxis.master import DEFAULT_EDS

pytestmark = pytest.mark.exclusive  # timing-sensitive: background jobs stopped meanwhile

GROUP, NODE, AXIS, NODE_ID = "plant7", "cell9", "X", 1


class PrimaryHost:
    """A primary-host-style subscriber of ``spBv1.0/<group>/#``: every message decoded, in arrival order."""

    def __init__(self, port: int, group: str = GROUP):
        self.msgs: list[tuple[str, dict]] = []
        self.bad: list[tuple[str, str]] = []
        self.lock = threading.Lock()
        self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=f"primary-host-{os.getpid()}")
        self.client.on_message = self._on_message
        self.client.on_connect = self._on_connect
        self.client.reconnect_delay_set(0.05, 0.5)
        self.group = group
        self.connects = 0
        self.client.connect("127.0.0.1", port)
        self.client.loop_start()
        self.wait(lambda: self.connects)
        time.sleep(0.2)

    def _on_connect(self, client, userdata, flags, reason_code, properties) -> None:
        if not reason_code.is_failure:
            client.subscribe(f"spBv1.0/{self.group}/#", qos=1)
            self.connects += 1

    def _on_message(self, client, userdata, m) -> None:
        if m.topic.split("/")[2] in ("NCMD", "DCMD"):
            return  # (commands: this host's own, some malformed on purpose)
        try:
            d = decode(m.payload)
        except Exception as exc:  # noqa: BLE001 - recorded, the test fails on it
            with self.lock:
                self.bad.append((m.topic, repr(exc)))
            return
        with self.lock:
            self.msgs.append((m.topic, d))

    def of(self, kind: str) -> list[dict]:
        with self.lock:
            return [d for t, d in self.msgs if t.split("/")[2] == kind]

    def wait(self, predicate, timeout_s: float = 20.0) -> None:
        end = time.monotonic() + timeout_s
        while not predicate():
            assert time.monotonic() < end, f"timed out; last messages: {[t for t, _ in self.msgs[-8:]]}"
            time.sleep(0.02)

    def command(self, kind: str, metrics: list[dict], device: str | None = None) -> None:
        topic = f"spBv1.0/{GROUP}/{kind}/{NODE}" + (f"/{device}" if device else "")
        self.client.publish(topic, encode_command(metrics, int(time.time() * 1000)), qos=0).wait_for_publish(5)

    def publish_raw(self, topic: str, payload: bytes) -> None:
        self.client.publish(topic, payload, qos=0).wait_for_publish(5)

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


def _aliases(birth: dict) -> dict[int, dict]:
    return {m["alias"]: m for m in birth["metrics"]}


def _data_values(host: PrimaryHost, birth: dict) -> list[dict]:
    """Each DDATA as ``{metric name: value}`` through the DBIRTH's aliases."""
    names = {a: m["name"] for a, m in _aliases(birth).items()}
    return [{names[m["alias"]]: m.get("value") for m in d["metrics"]} for d in host.of("DDATA")]


def _result(host: PrimaryHost, birth: dict, ident) -> dict:
    out = []

    def found() -> bool:
        for v in _data_values(host, birth):
            r = v.get("Fault Injection/Result")
            if r and json.loads(r).get("id") == ident:
                out.append(json.loads(r))
                return True
        return False

    host.wait(found)
    return out[0]


def _check_seq(host: PrimaryHost) -> None:
    """seq: 0 on each NBIRTH, then +1 (mod 256) on every DBIRTH / DDATA / DDEATH, in arrival order."""
    with host.lock:
        msgs = [(t.split("/")[2], d) for t, d in host.msgs if t.split("/")[2] not in ("NDEATH", "NCMD", "DCMD")]
    assert msgs and msgs[0][0] == "NBIRTH"
    expected = 0
    for kind, d in msgs:
        if kind == "NBIRTH":
            expected = 0
        assert d.get("seq", 0) == expected, (kind, d.get("seq"), expected)
        expected = (expected + 1) % 256


def _enable_csp(spec_kwargs: dict) -> None:
    net = canopen.Network()
    net.connect(**spec_kwargs)
    try:
        node = net.add_node(canopen.RemoteNode(NODE_ID, DEFAULT_EDS))
        node.nmt.state = "OPERATIONAL"
        time.sleep(0.1)
        node.sdo[0x6060].raw = 8
        for cw in (0x06, 0x07, 0x0F):
            node.sdo[0x6040].raw = cw
            time.sleep(0.05)
        end = time.monotonic() + 10
        while node.sdo[0x6041].raw & 0x6F != 0x27:
            assert time.monotonic() < end, f"not enabled: statusword 0x{node.sdo[0x6041].raw:04X}"
            time.sleep(0.05)
    finally:
        net.disconnect()


@pytest.mark.mqtt_broker
def test_primary_host_sees_births_data_rebirth_commands_and_the_will_of_a_killed_node(mosquitto):  # noqa: F811
    host = PrimaryHost(mosquitto.port)
    with served("--axis", f"{AXIS}={NODE_ID}:configs/seed000-hust.toml", "--mqtt", mosquitto.url, "--machine", NODE,
                "--sparkplug", GROUP, "--allow-fault-injection", "--telemetry-rate", "50",
                "--telemetry-batch", "5") as srv:
        host.wait(lambda: host.of("DBIRTH"), timeout_s=30)
        nbirth, dbirth = host.of("NBIRTH")[0], host.of("DBIRTH")[0]
        topics = {t for t, _ in host.msgs}
        assert f"spBv1.0/{GROUP}/NBIRTH/{NODE}" in topics and f"spBv1.0/{GROUP}/DBIRTH/{NODE}/{AXIS}" in topics
        node_metrics = {m["name"]: m for m in nbirth["metrics"]}
        bdseq = node_metrics["bdSeq"]["value"]
        assert bdseq == 0 and node_metrics["bdSeq"]["datatype"] == 8  # UInt64
        assert node_metrics["Node Control/Rebirth"]["value"] is False
        assert node_metrics["Node Control/Rebirth"]["datatype"] == 11  # Boolean
        # every birth metric: name, alias (unique in the edge node), datatype; units as the property engUnit
        births = nbirth["metrics"] + dbirth["metrics"]
        assert all("name" in m and "alias" in m and "datatype" in m for m in births)
        assert len({m["alias"] for m in births}) == len(births)
        by_name = {m["name"]: m for m in dbirth["metrics"]}
        assert by_name["Position"]["properties"] == {"engUnit": "mm"} and by_name["Position"]["datatype"] == 10
        assert by_name["Following Error"]["properties"] == {"engUnit": "um"}
        assert by_name["State/CiA402"]["value"] == "SWITCH ON DISABLED"
        # enabled in CSP by a CANopen master: DDATA (aliases only) report the mode and the state
        n0 = len(host.of("DDATA"))
        _enable_csp(srv.bus_kwargs())
        host.wait(lambda: any(v.get("State/CiA402") == "OPERATION ENABLED" for v in _data_values(host, dbirth)))
        host.wait(lambda: any(v.get("State/Mode") == 8 for v in _data_values(host, dbirth)))
        assert all("name" not in m and "datatype" not in m for d in host.of("DDATA") for m in d["metrics"])
        assert len(host.of("DDATA")) > n0
        # a fault command by DCMD (alias), answered in Fault Injection/Result
        cmd_alias = by_name["Fault Injection/Command"]["alias"]
        host.command("DCMD", [{"alias": cmd_alias, "datatype": 12, "value": json.dumps(
            {"action": "inject", "kind": "encoder_loss", "id": "fe1"})}], AXIS)
        res = _result(host, dbirth, "fe1")
        assert res["ok"] is True and "encoder_loss" in res["active"], res
        host.wait(lambda: any(v.get("State/Fault Active") is True for v in _data_values(host, dbirth)))
        host.command("DCMD", [{"name": "Fault Injection/Command", "datatype": 12,
                               "value": json.dumps({"action": "clear", "id": "c1"})}], AXIS)
        assert _result(host, dbirth, "c1")["active"] == []
        # bad commands: refused, answered, logged; nothing else is lost (seq stays gapless below)
        n_res = sum("Fault Injection/Result" in v for v in _data_values(host, dbirth))
        host.publish_raw(f"spBv1.0/{GROUP}/DCMD/{NODE}/{AXIS}", b"\xff\xff\xff not protobuf")
        host.command("DCMD", [{"name": "Position", "datatype": 12, "value": "1.0"}], AXIS)
        host.command("DCMD", [{"name": "Fault Injection/Command", "datatype": 12,
                               "value": '{"action":"inject","kind":"no_such_kind","id":"k"}'}], AXIS)
        host.command("DCMD", [{"alias": cmd_alias, "datatype": 11, "value": True}], AXIS)
        host.wait(lambda: sum("Fault Injection/Result" in v for v in _data_values(host, dbirth)) >= n_res + 4)
        answers = [json.loads(v["Fault Injection/Result"]) for v in _data_values(host, dbirth)
                   if "Fault Injection/Result" in v][n_res:]
        assert [a["ok"] for a in answers] == [False] * 4, answers
        errors = " | ".join(a["error"] for a in answers)
        assert "not a Sparkplug B payload" in errors and "'Position': not writable" in errors
        assert "must be a String" in errors and "no_such_kind" in errors
        host.command("NCMD", [{"name": "Node Control/Rebirth", "datatype": 11, "value": False}])
        # rebirth on request: a new NBIRTH (seq 0, the same bdSeq: the same connection) and DBIRTH
        host.command("NCMD", [{"name": "Node Control/Rebirth", "datatype": 11, "value": True}])
        host.wait(lambda: len(host.of("NBIRTH")) == 2 and len(host.of("DBIRTH")) == 2)
        reborn = {m["name"]: m["value"] for m in host.of("NBIRTH")[1]["metrics"]}
        assert reborn["bdSeq"] == bdseq and host.of("NBIRTH")[1]["seq"] == 0
        # (the DBIRTH of a rebirth carries the values of now: the state the DDATA reported last)
        last_state = [v["State/CiA402"] for v in _data_values(host, dbirth) if "State/CiA402" in v][-1]
        assert last_state == "FAULT"
        assert {m["name"]: m["value"] for m in host.of("DBIRTH")[1]["metrics"]}["State/CiA402"] == last_state
        host.wait(lambda: len(host.of("DDATA")) > 0 and host.msgs[-1][0].split("/")[2] == "DDATA")
        # kill -9: the broker publishes the will, an NDEATH with the bdSeq of the NBIRTH
        srv.proc.send_signal(signal.SIGKILL)
        host.wait(lambda: host.of("NDEATH"), timeout_s=30)
        srv.proc.wait(timeout=10)
    stderr = srv.stderr
    assert {m["name"]: m["value"] for m in host.of("NDEATH")[0]["metrics"]} == {"bdSeq": bdseq}
    assert not host.of("DDEATH")  # (killed: no clean stop)
    _check_seq(host)
    assert not host.bad, host.bad
    assert stderr.count("command refused") >= 4 and "Traceback" not in stderr, stderr[-3000:]
    host.close()


@pytest.mark.mqtt_broker
def test_clean_stop_sends_ddeath_and_ndeath_and_a_broker_restart_gives_a_new_bdseq(mosquitto):  # noqa: F811
    host = PrimaryHost(mosquitto.port)
    with served("--mqtt", mosquitto.url, "--machine", NODE, "--sparkplug", GROUP) as srv:
        host.wait(lambda: host.of("DBIRTH"), timeout_s=30)
        # without --allow-fault-injection a fault command by DCMD is refused as on fault/set
        dbirth = host.of("DBIRTH")[0]
        axis = next(t for t, _ in host.msgs if "/DBIRTH/" in t).split("/")[-1]  # (the config's axis name)
        host.command("DCMD", [{"name": "Fault Injection/Command", "datatype": 12, "value": json.dumps(
            {"action": "inject", "kind": "encoder_loss", "id": "no"})}], axis)
        res = _result(host, dbirth, "no")
        assert res["ok"] is False and res["abort_code"] == "0x08000022", res
        mosquitto.stop(kill=True)
        mosquitto.start()
        host.wait(lambda: host.connects >= 2, timeout_s=10)
        # the edge node's births may come before this subscriber is back: a primary host asks for a rebirth
        end = time.monotonic() + 30
        while len(host.of("NBIRTH")) < 2:
            assert time.monotonic() < end, "no NBIRTH after the broker restart"
            host.command("NCMD", [{"name": "Node Control/Rebirth", "datatype": 11, "value": True}])
            time.sleep(1.0)
        host.wait(lambda: len(host.of("DBIRTH")) >= 2)
        srv.stop()
    host.wait(lambda: host.of("NDEATH"))
    bdseqs = [{m["name"]: m["value"] for m in b["metrics"]}["bdSeq"] for b in host.of("NBIRTH")]
    assert bdseqs[0] == 0 and bdseqs[-1] > bdseqs[0]  # one per connection attempt
    assert {m["name"]: m["value"] for m in host.of("NDEATH")[-1]["metrics"]} == {"bdSeq": bdseqs[-1]}
    kinds = [t.split("/")[2] for t, _ in host.msgs]
    assert kinds[-2:] == ["DDEATH", "NDEATH"]
    assert srv.returncode == 0, srv.stderr[-2000:]
    host.close()


def _serve_error(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, "serve", "--can", "udp_multicast:239.74.163.9,port=47999", "--duration", "1", *args],
                          capture_output=True, text=True, timeout=60, cwd=ROOT, env={**os.environ, **(env or {})})


@pytest.mark.parametrize("args, words", [
    (["--sparkplug", "g1"], "--sparkplug need --mqtt"),
    (["--mqtt", "mqtt://127.0.0.1:1", "--sparkplug", "a/b"], "--sparkplug 'a/b': a group id takes"),
])
def test_bad_sparkplug_options_are_one_error_line(args, words):
    r = _serve_error(*args)
    assert r.returncode == 2 and words in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and r.stderr.count("error:") == 1


def test_without_protobuf_the_error_names_the_extra(tmp_path):
    shadow = tmp_path / "google"  # a package 'google' without protobuf shadows the installed one
    shadow.mkdir()
    (shadow / "__init__.py").write_text("")
    r = _serve_error("--mqtt", "mqtt://127.0.0.1:1", "--sparkplug",
                     env={"PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])})
    assert r.returncode == 2 and "pip install 'virtualaxis[sparkplug]'" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr


def test_the_docs_metric_table_is_the_one_the_node_publishes():
    from virtualaxis.services.sparkplug import metric_table_markdown

    page = (Path(ROOT) / "docs" / "side-channels.md").read_text()
    assert metric_table_markdown() in page


def test_seq_wraps_from_255_to_0_and_each_nbirth_starts_at_0():
    """The edge node's payloads in order (no broker: 600 messages would take a minute of a moving axis):
    NBIRTH 0, DBIRTH 1, DDATA 2..255, 0, 1, ...; a rebirth's NBIRTH is 0 again; aliases only in DDATA."""
    from virtualaxis.services.mqtt import MqttSettings
    from virtualaxis.services.sparkplug import SparkplugPublisher

    st = MqttSettings(host="127.0.0.1", port=1, machine=NODE, sparkplug_group=GROUP)
    pub = SparkplugPublisher(st, [{"name": AXIS, "node_id": 1, "lead_m": 0.016}], ring=None)
    ch = pub.channels[0]
    seqs = [decode(pub.node_birth_payload())["seq"], decode(pub.device_birth_payload(ch))["seq"]]
    for k in range(600):
        d = decode(pub.device_data_payload(ch, [(0, float(k), 1)]))
        assert [set(m) for m in d["metrics"]] == [{"alias", "timestamp", "value"}]
        seqs.append(d["seq"])
    assert seqs == [k % 256 for k in range(602)]
    assert decode(pub.node_birth_payload()).get("seq", 0) == 0
    assert decode(pub.device_birth_payload(ch))["seq"] == 1
