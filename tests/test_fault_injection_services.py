"""Issue #16: fault injection over the side channels, with real parts.

- Modbus TCP: ``virtualaxis serve --modbus --modbus-writable [--allow-fault-injection]`` in another process, a real
  pymodbus client writing the injection block 40600-40609 (docs/modbus-map.md) and a ``canopen`` master reading
  0x603F / 0x5FF5 by SDO: the drive faults with the kind's code, the reset is refused while the cause is injected,
  clear + reset recovers; refused with exception 04 (40499 = 3, 0x08000022) without --allow-fault-injection, an
  unknown kind with exception 03 (40499 = 4, 0x06090030).
- MQTT: ``virtualaxis serve --mqtt`` against a real mosquitto broker, a real paho client publishing on
  ``virtualaxis/<machine>/<axis>/fault/set``: the ``fault/result`` answer, the ``faults`` event with the EMCY code;
  malformed commands answered ``ok: false`` naming what is wrong while serve goes on serving. Every message
  virtualaxis publishes is validated against its schema in docs/schemas/.
"""

from __future__ import annotations

import json
import time

import canopen
import pytest
from pymodbus.client import ModbusTcpClient
from served_drive import served
from services_fixtures import ON_BOTH_BROKERS, mosquitto  # noqa: F401 (fixture)
from test_services_mqtt import SCHEMAS

from virtualaxis.drive.injection import KINDS
from virtualaxis.master import DEFAULT_EDS, connect
from virtualaxis.services.mqtt import apply_fault_command, parse_fault_command

#: a kind number no fault kind has
UNKNOWN_KIND = max(KINDS.values()) + 1

pytestmark = pytest.mark.exclusive  # timing-sensitive: background jobs stopped meanwhile

A = 40001  # register number -> PDU address
FI_DUTY, FI_PERIOD, FI_MAGNITUDE, FI_INJECT, FI_CLEAR, FI_ACTIVE, FI_ALLOWED = (
    40600, 40601, 40603, 40605, 40606, 40607, 40609)
STW1, STATE, ERROR_CODE, FAULT_CODE_0, LAST_ERROR_ADDRESS = 40100, 40118, 40121, 40410, 40496
FAULT, SWITCH_ON_DISABLED, OPERATION_ENABLED = 7, 1, 4


def _wait(predicate, timeout: float = 5.0, what: str = "condition"):
    end = time.monotonic() + timeout
    while not (value := predicate()):
        assert time.monotonic() < end, f"{what} not reached in {timeout} s"
        time.sleep(0.01)
    return value


def _side_line(srv, prefix: str) -> str:
    """The line serve prints for a side channel after its ready line (``modbus: HOST:PORT ...``)."""
    line = srv.proc.stdout.readline()
    assert line.startswith(prefix), line
    return line


class Modbus:
    def __init__(self, srv):
        port = int(_side_line(srv, "modbus:").split()[1].rsplit(":", 1)[1])
        self.c = ModbusTcpClient("127.0.0.1", port=port, timeout=3)
        assert self.c.connect()

    def read(self, number: int, count: int = 1) -> list[int]:
        r = self.c.read_holding_registers(number - A, count=count, device_id=1)
        assert not r.isError(), f"read {number}: {r}"
        return list(r.registers)

    def u32(self, number: int) -> int:
        hi, lo = self.read(number, 2)
        return hi << 16 | lo

    def write(self, number: int, *values: int):
        if len(values) == 1:
            return self.c.write_register(number - A, values[0], device_id=1)
        return self.c.write_registers(number - A, list(values), device_id=1)

    def ok(self, number: int, *values: int) -> None:
        r = self.write(number, *values)
        assert not r.isError(), f"write {number} {values}: {r}"

    def refused(self, number: int, *values: int) -> tuple[int, int, int, int]:
        """(exception code, 40499 reason, 40496 address, 40497-98 abort code) of a refused write."""
        r = self.write(number, *values)
        assert r.isError(), f"write {number} {values} was accepted"
        w = self.read(LAST_ERROR_ADDRESS, 4)  # (right after a refusal the unit's image is fresh)
        return r.exception_code, w[3], w[0], w[1] << 16 | w[2]

    def state(self) -> int:
        return self.read(STATE)[0]


def test_modbus_injects_dc_link_undervoltage_and_clears_it():
    with served("--modbus", "127.0.0.1:0", "--modbus-writable", "--allow-fault-injection") as srv:
        mb = Modbus(srv)
        net = connect(srv.spec)
        node = canopen.RemoteNode(1, DEFAULT_EDS)
        net.add_node(node)
        try:
            assert mb.read(FI_ALLOWED) == [1] and mb.u32(FI_ACTIVE) == 0
            assert mb.read(FI_DUTY, 5) == [0, 0, 1000, 0, 0]  # defaults: permanent, 1 s, magnitude 0
            mb.ok(40102, 8)  # CSP, enabled through STW1: the fault reaction runs from OPERATION ENABLED
            mb.ok(STW1, 0x047E)
            mb.ok(STW1, 0x047F)
            _wait(lambda: mb.state() == OPERATION_ENABLED, what="operation enabled")
            # options and the kind in one FC16 request (applied in address order): permanent, 1 s, default magnitude
            mb.ok(FI_DUTY, 0, 0, 1000, 0, 0, 4)
            _wait(lambda: mb.state() == FAULT, what="FAULT")
            assert mb.read(ERROR_CODE) == [0x3220] and mb.read(FAULT_CODE_0) == [0x3220]
            assert mb.u32(FI_ACTIVE) == 1 << 3 and mb.read(FI_INJECT) == [4]
            assert node.sdo[0x603F].raw == 0x3220  # what a CANopen master reads
            assert node.sdo[0x5FF5].raw == 1 << 3  # the CAN channel sees the same injection
            mb.ok(STW1, 0x04FE)  # acknowledge: refused while the supply is still lost
            time.sleep(0.1)
            assert mb.state() == FAULT
            # an unknown kind: exception 03, the drive's abort code recorded; nothing changes
            assert mb.refused(FI_INJECT, UNKNOWN_KIND) == (3, 4, FI_INJECT - A, 0x06090030)
            assert mb.refused(FI_CLEAR, 12) == (3, 4, FI_CLEAR - A, 0x06090030)
            assert mb.refused(FI_DUTY, 1001) == (3, 4, FI_DUTY - A, 0x06090030)
            assert mb.refused(FI_PERIOD, 0, 1) == (3, 4, FI_PERIOD - A, 0x06090030)
            assert mb.refused(FI_ACTIVE, 0, 0)[:2] == (4, 2)  # read-only
            assert mb.u32(FI_ACTIVE) == 1 << 3
            mb.ok(FI_CLEAR, 4)
            assert mb.u32(FI_ACTIVE) == 0 and mb.read(FI_CLEAR) == [4]
            assert node.sdo[0x5FF5].raw == 0
            mb.ok(STW1, 0x047E)
            mb.ok(STW1, 0x04FE)  # acknowledge (rising edge of bit 7)
            _wait(lambda: mb.state() == SWITCH_ON_DISABLED, what="fault reset accepted after clear")
            # intermittent: duty 500 per mille of 200 ms with a magnitude, then clear all (255)
            mb.ok(FI_DUTY, 500, 0, 200, 0, 0)
            mb.ok(FI_INJECT, 1)
            assert mb.read(FI_DUTY, 5) == [500, 0, 200, 0, 0] and mb.u32(FI_ACTIVE) == 1
            _wait(lambda: mb.state() == FAULT, what="intermittent encoder loss")
            assert mb.read(ERROR_CODE) == [0x7305]
            mb.ok(FI_CLEAR, 255)
            assert mb.u32(FI_ACTIVE) == 0
        finally:
            mb.c.close()
            net.disconnect()
    assert srv.returncode == 0, srv.stderr[-2000:]


def test_modbus_injection_registers_without_an_injector_or_writes():
    """In process: an ``AxisLink`` without an injector answers as "not allowed"; without --modbus-writable the
    writes are refused by the Modbus layer first (reason 1)."""
    from test_services_modbus import Server, make_drive

    from virtualaxis.drive.injection import FaultInjector
    from virtualaxis.services.modbus_map import AxisLink, read_block

    drive = make_drive()
    link = AxisLink(drive, 1)
    assert read_block(link, FI_ALLOWED - A, 1) == [0]
    srv = Server({1: drive})  # writable, no injector
    try:
        assert srv.exc(srv.client.write_register(FI_INJECT - A, 4, device_id=1)) == 4
        assert srv.last_error() == (3, FI_INJECT - A, 0x08000022)
    finally:
        srv.close()
    ro = Server({1: drive}, writable=False)
    ro.links[1].injector = FaultInjector(drive, allowed=True)
    try:
        assert ro.read(FI_ALLOWED) == [1]
        assert ro.exc(ro.client.write_register(FI_INJECT - A, 4, device_id=1)) == 4
        assert ro.last_error()[0] == 1
        assert drive.state.cia402_state != "FAULT"
    finally:
        ro.close()


# ---------------------------------------------------------------------------------------------- MQTT
def _axis_name(srv) -> str:
    return srv.ready_line.split("serving ", 1)[1].split(" (node", 1)[0]


class Commands:
    """A paho subscriber to virtualaxis/# (every message virtualaxis publishes validated against its schema, as
    in test_services_mqtt) that also publishes fault/set commands of one axis and waits for their results."""

    def __init__(self, port: int):
        from test_services_mqtt import Subscriber

        self.sub = Subscriber(port)
        self.prefix = ""

    def at(self, machine: str, axis: str) -> Commands:
        self.prefix = f"virtualaxis/{machine}/{axis}/"
        return self

    def publish(self, payload, *, retain: bool = False) -> None:
        if isinstance(payload, dict):
            payload = json.dumps(payload)
        info = self.sub.client.publish(self.prefix + "fault/set", payload, qos=1, retain=retain)
        info.wait_for_publish(5)

    def results(self) -> list[dict]:
        return self.sub.of("fault/result")

    def result(self, ident=None, *, after: int = 0, timeout: float = 10.0) -> dict:
        """The result with ``id`` ``ident`` (None: the first without an id among results ``after`` on)."""
        def find():
            for r in self.results()[after:]:
                if r.get("id") == ident:
                    return r
            return None

        return self.sub.wait(find, timeout)


@pytest.mark.mqtt_broker
@ON_BOTH_BROKERS
def test_mqtt_inject_result_fault_event_malformed_commands_and_serve_goes_on(mosquitto):  # noqa: F811
    cmd = Commands(mosquitto.port)
    machine = "cell9"
    # a retained command left on the broker: replayed at each subscription, never applied
    cmd.at(machine, "X").publish({"action": "inject", "kind": "encoder_loss", "id": "stale"}, retain=True)
    with served("--axis", "X=1:configs/seed000-hust.toml", "--mqtt", mosquitto.url, "--machine", machine,
                "--allow-fault-injection") as srv:
        _side_line(srv, "mqtt:")
        axis = _axis_name(srv)
        assert axis == "X"
        sub = cmd.sub
        # (30 s: on a host with other work the broker connection has taken more than 10 s)
        sub.wait(lambda: any(s["status"] == "online" for s in sub.of("status")), 30.0)
        stale = cmd.result("stale")
        assert stale["ok"] is False and "retained" in stale["error"] and "active" not in stale
        cmd.publish({"action": "inject", "kind": "dc_link_undervoltage", "id": "c1"})
        r = cmd.result("c1")  # (answered within the result's 10 s; how fast is no test's to judge)
        assert r["ok"] is True and r["action"] == "inject" and r["active"] == ["dc_link_undervoltage"], r
        assert r["machine"] == machine and r["axis"] == "X" and r["node_id"] == 1
        ev = sub.wait(lambda: [f for f in sub.of("faults") if f["event"] == "fault"])[0]
        assert ev["emcy_code"] == "0x3220" and ev["error_code"] == "0x3220" and ev["injected"] is True, ev
        sub.wait(lambda: any(s["cia402_state"] == "FAULT" and s["error_code"] == "0x3220" for s in sub.of("state")))
        # a command published with retain=true while serve listens: refused too on an MQTT 5 broker
        # (retain-as-published); through an MQTT 3.1.1 broker it reaches serve as a plain one and is applied
        cmd.publish({"action": "clear", "kind": "encoder_loss", "id": "live-retained"}, retain=True)
        live = cmd.result("live-retained")
        if mosquitto.mqtt5:
            assert live["ok"] is False and "retained" in live["error"], live
        else:
            assert live["ok"] is True and live["active"] == ["dc_link_undervoltage"], live
        # malformed / refused commands: one ok:false result each, naming what is wrong
        n = len(cmd.results())
        bad = [
            (b"{oops", None, "not JSON"),
            (b"[1, 2]", None, "JSON object"),
            (b"\xff\xfe", None, "UTF-8"),
            ({"action": "inject", "kind": "encoder_loss", "dutty": 0.5, "id": 7}, 7, "'dutty'"),
            ({"action": "inject", "kind": "encoder_loss", "duty": "half", "id": 8}, 8, "duty: must be a number"),
            ({"action": "explode", "id": 9}, 9, "action"),
            ({"action": "inject", "id": 10}, 10, "kind: missing"),
            ({"action": "clear", "kind": "encoder_loss", "period_s": 1, "id": 11}, 11, "period_s: only with"),
            ({"action": "inject", "kind": [1], "id": 12}, 12, "kind: must be"),
            ({"action": "inject", "kind": "encoder_loss", "id": {"x": 1}}, None, "id: must be"),
            (b"[" * 3000, None, "nested too deeply"),
            (b"{" + b" " * 5000 + b"}", None, "at most 4096"),
        ]
        for payload, _, _ in bad:
            cmd.publish(payload)
        sub.wait(lambda: len(cmd.results()) >= n + len(bad))
        got = cmd.results()[n:]
        assert len(got) == len(bad)
        for (payload, ident, words), res in zip(bad, got, strict=True):  # answered in order (one connection)
            assert res["ok"] is False and words in res["error"], (payload, res)
            assert res.get("id") == ident and "abort_code" not in res and "active" not in res, (payload, res)
            if isinstance(payload, dict):
                assert not SCHEMAS["fault/set"].is_valid(payload), payload
        # refused by the drive's injector (well-formed): the abort code, and what stays injected
        cmd.publish({"action": "inject", "kind": "no_such_kind", "id": "c3"})
        cmd.publish({"action": "inject", "kind": UNKNOWN_KIND, "id": "c4"})
        cmd.publish({"action": "inject", "kind": "encoder_loss", "duty": 2.0, "id": "c5"})
        for ident in ("c3", "c4", "c5"):
            r = cmd.result(ident)
            assert r["ok"] is False and r["abort_code"] == "0x06090030", r
            assert r["active"] == ["dc_link_undervoltage"], r
        # a burst of 200 commands sent back to back: every one gets its result (ok, or "busy" beyond 16 in flight)
        n = len(cmd.results())
        for k in range(200):
            cmd.sub.client.publish(cmd.prefix + "fault/set", json.dumps(
                {"action": "clear", "kind": "encoder_loss", "id": f"b{k}"}), qos=1)
        wanted = {f"b{k}" for k in range(200)}
        sub.wait(lambda: wanted <= {r.get("id") for r in cmd.results()[n:]}, timeout=30)
        burst = [r for r in cmd.results()[n:] if r.get("id") in wanted]
        assert len(burst) == 200 and all(r["ok"] or "busy" in r["error"] for r in burst), burst[:3]
        # serve goes on serving: telemetry keeps coming, then a clear and an intermittent injection by number
        samples = sub.samples()
        sub.wait(lambda: sub.samples() >= samples + 20)
        assert srv.proc.poll() is None
        for c in ({"action": "clear", "id": "c6"},
                  {"action": "inject", "kind": 1, "duty": 0.5, "period_s": 0.2, "magnitude": None, "id": 13}):
            assert SCHEMAS["fault/set"].is_valid(c), c
            cmd.publish(c)
        assert cmd.result("c6")["active"] == [] and cmd.result("c6")["ok"] is True
        assert cmd.result(13)["active"] == ["encoder_loss"] and cmd.result(13)["kind"] == 1
        sub.wait(lambda: any(f["emcy_code"] == "0x7305" for f in sub.of("faults")))
        assert sub.invalid == [], sub.invalid[:3]
    assert srv.returncode == 0, srv.stderr[-2000:]
    assert "Traceback" not in srv.stderr, srv.stderr[-2000:]
    cmd.sub.close()


@pytest.mark.mqtt_broker
def test_injection_refused_on_both_channels_without_allow_fault_injection(mosquitto):  # noqa: F811
    """One serve without --allow-fault-injection: Modbus exception 04 (40499 = 3, 0x08000022) and an MQTT
    ``ok: false`` result with abort code 0x08000022; the drive does not fault."""
    cmd = Commands(mosquitto.port)
    with served("--modbus", "127.0.0.1:0", "--modbus-writable", "--mqtt", mosquitto.url, "--machine", "cell3") as srv:
        mb = Modbus(srv)
        _side_line(srv, "mqtt:")
        cmd.at("cell3", _axis_name(srv))
        sub = cmd.sub
        try:
            assert mb.read(FI_ALLOWED) == [0]
            # every write of the block: exception 04, reason 3 (drive state), abort 0x08000022; the unknown
            # kind too (the permission is checked first, as on CAN)
            for number, values in ((FI_INJECT, (4,)), (FI_INJECT, (UNKNOWN_KIND,)), (FI_CLEAR, (0,)), (FI_DUTY, (500,)),
                                   (FI_PERIOD, (0, 200)), (FI_MAGNITUDE, (0, 5)), (FI_DUTY, (0, 0, 1000, 0, 0, 4))):
                assert mb.refused(number, *values) == (4, 3, number - A, 0x08000022), (number, values)
            assert mb.u32(FI_ACTIVE) == 0 and mb.read(FI_DUTY, 5) == [0, 0, 1000, 0, 0]
            sub.wait(lambda: any(s["status"] == "online" for s in sub.of("status")))
            for ident, c in (("r1", {"action": "inject", "kind": "dc_link_undervoltage"}),
                             ("r2", {"action": "clear"}),
                             ("r3", {"action": "inject", "kind": 99})):
                cmd.publish(c | {"id": ident})
                r = cmd.result(ident)
                assert r["ok"] is False and r["abort_code"] == "0x08000022", r
                assert "--allow-fault-injection" in r["error"] or "off" in r["error"], r
                assert r["active"] == [], r
            time.sleep(0.2)
            assert mb.state() != FAULT and mb.read(ERROR_CODE) == [0]
            assert not sub.of("faults")
            assert sub.invalid == [], sub.invalid[:3]
        finally:
            mb.c.close()
    assert srv.returncode == 0, srv.stderr[-2000:]
    cmd.sub.close()


def test_fault_command_form_and_application_without_io():
    """parse_fault_command (the publisher process' check) and apply_fault_command (serve's) on their own."""
    from test_services_modbus import make_drive

    from virtualaxis.drive.injection import FaultInjector

    cmd, err = parse_fault_command(b'{"action": "inject", "kind": "over_current", "duty": 1, "magnitude": 3, "id": 5}')
    assert err is None and cmd == {"id": 5, "action": "inject", "kind": "over_current",
                                   "options": {"duty": 1.0, "magnitude": 3.0}}
    assert parse_fault_command('{"action": "clear"}')[0] == {"action": "clear", "kind": None, "options": {}}
    # 4.0 is an integer to JSON Schema (docs/schemas/fault-set.schema.json accepts it): the kind number 4
    assert parse_fault_command('{"action": "inject", "kind": 4.0}')[0]["kind"] == 4
    assert parse_fault_command('{"action": "inject", "kind": 4.5}')[1]["ok"] is False
    for payload, words in ((None, "not JSON"), (b"", "not JSON"), (b'{"action": "inject", "kind": 1, "duty": NaN}',
                           "NaN"), (b'{"action": "inject", "kind": 1, "magnitude": 1e999}', "finite"),
                           (b'{"action": "inject", "kind": 1, "magnitude": 1' + b"0" * 400 + b"}", "out of range"),
                           (b'{"action": "inject", "kind": true}', "kind: must be"),
                           (b'{"action": "inject", "kind": 1, "duty": false}', "duty: must be a number"),
                           (b'{"id": "' + b"x" * 200 + b'"}', "id: must be")):
        c, res = parse_fault_command(payload)
        assert c is None and res["ok"] is False and words in res["error"], (payload, res)
    drive = make_drive()
    r = apply_fault_command(None, {"action": "inject", "kind": 1, "options": {}, "id": "a"})
    assert r == {"id": "a", "action": "inject", "kind": 1, "ok": False, "abort_code": "0x08000022", "active": [],
                 "error": "fault injection is not available on this axis"}
    inj = FaultInjector(drive, allowed=True)
    r = apply_fault_command(inj, {"action": "inject", "kind": "limit_switch", "options": {"magnitude": 1.0}})
    assert r["ok"] is True and r["active"] == ["limit_switch"]
    r = apply_fault_command(inj, {"action": "inject", "kind": 4, "options": {"duty": 0.5, "period_s": 0.001}})
    assert r["ok"] is False and r["abort_code"] == "0x06090030" and "period_s" in r["error"]
    # a permanent fault has no period: any value is accepted, 0 included (as OPC UA's PeriodS 0 with Duty 1)
    r = apply_fault_command(inj, {"action": "inject", "kind": 4, "options": {"duty": 1.0, "period_s": 0.0}})
    assert r["ok"] is True and "dc_link_undervoltage" in r["active"], r
    r = apply_fault_command(inj, {"action": "clear", "kind": None, "options": {}})
    assert r == {"action": "clear", "ok": True, "active": []}
    inj.allowed = False
    r = apply_fault_command(inj, {"action": "clear", "kind": None, "options": {}})
    assert r["ok"] is False and r["abort_code"] == "0x08000022"
