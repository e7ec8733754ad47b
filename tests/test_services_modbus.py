"""Modbus TCP side channel: a real pymodbus client against the server of `virtualaxis.services.modbus`.

Every register is compared with the drive's own state during a CSP move (the expected values below are
written from docs/modbus-map.md, not from the map's code), every exception code is provoked, writes are
checked to apply live (Kv written by Modbus changes the following error; STW1 bit 7 acknowledges a fault)
and to agree with what a CANopen master reads by SDO.
"""

from __future__ import annotations

import math
import socket
import struct
import time
from pathlib import Path

import pytest
from pymodbus.client import ModbusTcpClient
from test_drive_rig import Rig, seed_config, seed_discrete

from virtualaxis.drive import Drive
from virtualaxis.services.modbus import ModbusService
from virtualaxis.services.modbus_map import REGISTERS, AxisLink, render_markdown

pytestmark = pytest.mark.exclusive  # timing-sensitive: background jobs stopped meanwhile

ROOT = Path(__file__).resolve().parents[1]


def make_drive(name: str = "X") -> Drive:
    return Drive(seed_config(), name=name, discrete=seed_discrete())


class Server:
    def __init__(self, drives: dict[int, Drive], writable: bool = True):
        self.links = {uid: AxisLink(d, uid) for uid, d in drives.items()}
        self.svc = ModbusService(list(self.links.values()), host="127.0.0.1", port=0, writable=writable).start()
        self.port = self.svc.bound_port
        self.client = ModbusTcpClient("127.0.0.1", port=self.port, timeout=3)
        assert self.client.connect()

    def read(self, number: int, count: int = 1, unit: int = 1, fc: int = 3) -> list[int]:
        """Registers as a client reads them once the drive's present state is published: reads are answered
        from an image published every ``image_period_s``, so wait for one publication that started after the
        drive was last changed (the tests step the drive by hand; it does not move while they read)."""
        self.svc.sync()
        f = self.client.read_holding_registers if fc == 3 else self.client.read_input_registers
        r = f(number - 40001, count=count, device_id=unit)
        assert not r.isError(), f"read {number} x{count}: {r}"
        return list(r.registers)

    def exc(self, response) -> int:
        assert response.isError(), f"expected an exception, got {response}"
        return response.exception_code

    def raw(self, pdu: bytes, unit: int = 1) -> bytes:
        """A hand-made request (for what the pymodbus client refuses to send): returns the response PDU."""
        with socket.create_connection(("127.0.0.1", self.port), timeout=3) as s:
            s.sendall(struct.pack(">HHHB", 0x1234, 0, len(pdu) + 1, unit) + pdu)
            data = s.recv(260)
        tid, proto, length, uid = struct.unpack(">HHHB", data[:7])
        assert (tid, proto, uid) == (0x1234, 0, unit) and length == len(data) - 6
        return data[7:]

    def last_error(self, unit: int = 1) -> tuple[int, int, int]:
        """(40499 reason, 40496 address, 40497-98 SDO abort code)."""
        w = self.read(40496, 4, unit)
        return w[3], w[0], (w[1] << 16) | w[2]

    def close(self):
        self.client.close()
        self.svc.stop()


@pytest.fixture
def server():
    s = Server({1: make_drive()})
    yield s
    s.close()


def s16(x: float) -> int:
    v = int(round(x))
    return max(-0x8000, min(0x7FFF, v))


def u16(x: float) -> int:
    return max(0, min(0xFFFF, int(round(x))))


def s32(x: float) -> int:
    return max(-0x80000000, min(0x7FFFFFFF, int(round(x))))


def u32(x: float) -> int:
    return max(0, min(0xFFFFFFFF, int(round(x))))


def words(value: int, n: int) -> list[int]:
    v = value & (0xFFFF if n == 1 else 0xFFFFFFFF)
    return [v] if n == 1 else [v >> 16, v & 0xFFFF]


def expected_registers(drive: Drive, ref_rpm: float) -> dict[int, list[int]]:
    """register number -> words, from docs/modbus-map.md's definitions and the drive's own API."""
    s = drive.state
    lead = seed_config().mechanics.lead_m
    rpm = 60.0 / lead
    unit_m = 1e-6  # the seed config's position unit
    p = drive.get_parameter
    o = drive.read_object
    norm = 0x4000 / ref_rpm * rpm
    state_code = {
        "SWITCH ON DISABLED": 1,
        "READY TO SWITCH ON": 2,
        "SWITCHED ON": 3,
        "OPERATION ENABLED": 4,
        "QUICK STOP ACTIVE": 5,
        "FAULT REACTION ACTIVE": 6,
        "FAULT": 7,
    }[s.cia402_state]
    sw = s.statusword
    zsw1 = sw & 0x02FF
    zsw1 |= (abs(s.velocity_actual_m_s - s.velocity_demand_m_s) <= o(0x606D) * unit_m) << 8
    zsw1 |= bool(sw & 0x400) << 10
    zsw1 |= (not sw & 0x800) << 11
    zsw1 |= (s.cia402_state == "OPERATION ENABLED") << 12
    zsw1 |= (s.alarm_number != 7910) << 13
    zsw1 |= (s.velocity_actual_m_s >= 0) << 14
    zsw1 |= 1 << 15
    omega = s.velocity_actual_m_s / lead * 2 * math.pi
    e: dict[int, list[int]] = {
        40100: words(s.controlword, 1),
        40101: words(s16(s.velocity_demand_m_s * norm), 1),
        40102: words(s16(o(0x6060)), 1),
        40110: words(zsw1, 1),
        40111: words(s16(s.velocity_actual_m_s * norm), 1),
        40112: words(s32(s.position_actual_m * 1e6), 2),
        40114: words(s32(s.following_error_m * 1e6), 2),
        40116: words(s32(s.position_demand_m * 1e6), 2),
        40118: words(state_code, 1),
        40119: words(s16(s.mode), 1),
        40120: words(sw, 1),
        40121: words(s.error_code, 1),
        40300: words(0, 1),  # power unit code number (SINAMICS r0200; the simulated one has none)
        40301: words(100, 1),  # version 0.1.0
        40321: words(u16(p("current_limit_a") * 10), 1),
        40324: words(u16(ref_rpm), 1),
        40340: words(s16(s.velocity_demand_m_s * rpm), 1),
        40341: words(s16(s.velocity_actual_m_s * rpm), 1),
        40342: words(u16(o(0x6080)), 1),
        40343: words(s16(s.velocity_actual_m_s * 6000), 1),
        40344: words(u16(s.dc_link_v), 1),
        40345: words(s16(s.current_a * 100), 1),
        40346: words(s16(s.torque_nm * 100), 1),
        40347: words(s16(s.torque_nm * omega / 1000 * 100), 1),
        40348: words(s32(s.table_position_m * 1e6), 2),
        40350: words(s32(s.velocity_actual_m_s * 1e6), 2),
        40352: words(s32(s.velocity_demand_m_s * 1e6), 2),
        40354: words(s16(o(0x6077)), 1),
        40355: words(s16(o(0x6078)), 1),
        40356: words(s.digital_inputs, 1),
        40357: words(int(s.homed), 1),
        40358: words(s16(p("motor_temperature_alarm_c")), 1),
        40359: words(s16(p("motor_temperature_fault_c")), 1),
        40360: words(s16(s.motor_temperature_c * 10), 1),
        40361: words(u16(p("kv_1000_per_min") * 100), 1),
        40362: words(u16(p("velocity_ff_factor") * 1000), 1),
        40363: words(u16(p("speed_kp") * 1000), 1),
        40364: words(u16(p("speed_tn_ms") * 10), 1),
        40365: words(u32(o(0x6065)), 2),
        40367: words(u16(o(0x6066)), 1),
        40368: words(u32(p("standstill_window_m") * 1e6), 2),
        40370: words(u16(o(0x2007)), 1),
        40371: words(u32(p("positioning_window_m") * 1e6), 2),
        40373: words(u16(o(0x6068)), 1),
        40374: words(u16(o(0x2002)), 1),
        40375: words(s16(p("external_force_n")), 1),
        40376: words(u32(s.cycles), 2),
        40378: words(u32(drive.counters["overruns"]), 2),
        40380: words(u32(drive.counters["faults_raised"]), 2),
        40382: words(u32(s.time_s * 1000), 2),
        40408: words(s.alarm_number, 1),
        40409: words(0, 1),  # alarm code (SINAMICS 40409; no alarm in this move)
        40419: words(len(s.faults), 1),
    }
    for i in range(8):
        f = s.faults[i] if i < len(s.faults) else None
        e[40400 + i] = words(f.fault_number if f else 0, 1)
        e[40410 + i] = words(f.emcy_code if f else 0, 1)
        e[40420 + 2 * i] = words(s32(f.value) if f else 0, 2)
    return e


def csp_enable(drive: Drive) -> None:
    drive.set_parameter("mode_of_operation", 8)
    for cw in (0x06, 0x07, 0x0F):
        drive.set_controlword(cw)
        drive.step(1)
    assert drive.state.cia402_state == "OPERATION ENABLED"


def csp_ramp(drive: Drive, v_m_s: float, n: int, x0_m: float = 0.0) -> float:
    """Constant-velocity CSP targets for ``n`` cycles (1 ms); returns the last target [m]."""
    x = x0_m
    for _ in range(n):
        x += v_m_s * drive.cycle_s
        drive.write_object(0x607A, 0, int(round(x * 1e6)))
        drive.step(1)
    return x


def test_modbus_map_document_is_generated_from_the_map():
    doc = (ROOT / "docs" / "modbus-map.md").read_text()
    assert doc == render_markdown(), (
        "docs/modbus-map.md differs from the register map: run "
        "`python3 -m virtualaxis.services.modbus_map --write docs/modbus-map.md`"
    )
    for r in REGISTERS:  # and every register is in it
        assert f"| {r.number}" in doc


def test_every_register_matches_the_drive_state_during_a_move(server):
    drive = server.links[1].drive
    drive.inject_fault(0x7305, 1234)  # fill the fault buffer with two entries first
    drive.clear_fault()
    drive.inject_fault(0x4210, -77)
    drive.clear_fault()
    csp_enable(drive)
    csp_ramp(drive, 0.05, 300)  # 50 mm/s, mid-move (accelerating into a constant speed)
    assert abs(drive.state.velocity_actual_m_s) > 0.01 and abs(drive.state.following_error_m) > 1e-6
    expected = expected_registers(drive, ref_rpm=seed_config().motor.rated_speed_rpm)
    ranges = [(40100, 40102), (40110, 40121), (40300, 40301), (40321, 40321), (40324, 40324), (40340, 40383),
              (40400, 40417), (40419, 40435)]
    got: dict[int, int] = {}
    for fc in (3, 4):
        for a, b in ranges:
            for i, w in enumerate(server.read(a, b - a + 1, fc=fc)):
                assert got.setdefault(a + i, w) == w  # FC04 reads the same map
    checked = 0
    for number, ws in expected.items():
        for i, w in enumerate(ws):
            assert got[number + i] == w, f"register {number + i}: got {got[number + i]}, expected {w}"
            checked += 1
    assert checked == len(got) - 0  # every register read was checked
    assert got[40112] == 0 or got[40113] != 0  # 32-bit position: high word first
    assert got[40400] == 30004 and got[40401] == 31100 and got[40410] == 0x4210
    assert (got[40420] << 16 | got[40421]) - (1 << 32) == -77  # signed 32-bit, high word first


def test_32_bit_saturation_and_sign():
    drive = make_drive()
    link = AxisLink(drive, 1)
    from virtualaxis.services.modbus_map import read_block

    csp_enable(drive)
    csp_ramp(drive, -0.08, 200)
    w = read_block(link, 40112 - 40001, 2)
    pos_um = round(drive.state.position_actual_m * 1e6)
    assert pos_um < 0 and ((w[0] << 16) | w[1]) - (1 << 32) == pos_um
    link.reference_speed_rpm = 1  # 0x4000 = 1 rpm: the normalised speed saturates, never wraps
    assert read_block(link, 40111 - 40001, 1) == [0x8000]  # -32768


def test_exception_codes_and_last_error_register():
    drive = make_drive()
    srv = Server({1: drive}, writable=True)
    ro = Server({1: drive}, writable=False)
    try:
        c = srv.client
        # 01: unsupported functions (a known one the map does not serve, and an unknown one)
        assert srv.exc(c.read_coils(0, count=1, device_id=1)) == 1
        assert srv.raw(bytes([0x41, 0, 0])) == bytes([0xC1, 0x01])
        assert srv.raw(bytes([0x08, 0, 0, 0x12, 0x34])) == bytes([0x88, 0x01])
        assert srv.last_error()[0] == 9
        # 02: unknown register, range crossing a hole, read past the end of a range
        assert srv.exc(c.read_holding_registers(0, count=1, device_id=1)) == 2
        assert srv.last_error()[:2] == (7, 0)
        assert srv.exc(c.read_holding_registers(40120 - 40001, count=5, device_id=1)) == 2
        assert srv.last_error()[:2] == (7, 40122 - 40001)  # the first hole
        assert srv.exc(c.read_input_registers(40499 - 40001, count=2, device_id=1)) == 2
        assert srv.exc(c.write_register(40103 - 40001, 1, device_id=1)) == 2
        # 03: counts (the pymodbus client refuses to send these: raw requests)
        assert srv.raw(struct.pack(">BHH", 3, 109, 0)) == bytes([0x83, 0x03])
        assert srv.raw(struct.pack(">BHH", 3, 109, 126)) == bytes([0x83, 0x03])
        assert srv.raw(struct.pack(">BHH", 4, 109, 126)) == bytes([0x84, 0x03])
        assert srv.exc(c.read_holding_registers(0, count=1, device_id=1)) == 2  # (another reason in 40499 first)
        assert srv.raw(struct.pack(">BHHB", 16, 360, 124, 248) + bytes(248)) == bytes([0x90, 0x03])
        assert srv.last_error()[:2] == (8, 360)
        # 03: half of a 32-bit pair, a value the drive refuses (SDO abort code in 40497-98)
        assert srv.exc(c.write_register(40365 - 40001, 5, device_id=1)) == 3
        assert srv.last_error() == (6, 40365 - 40001, 0)
        assert srv.exc(c.write_registers(40366 - 40001, [0, 5], device_id=1)) == 3  # starts on the low word
        assert srv.exc(c.write_register(40374 - 40001, 3, device_id=1)) == 3  # feed-forward mode 0..2
        assert srv.last_error() == (4, 40374 - 40001, 0x06090031)
        assert srv.exc(c.write_register(40102 - 40001, 2, device_id=1)) == 3  # mode 2 is not supported
        assert srv.last_error()[2] == 0x06090030
        assert srv.exc(c.write_register(40324 - 40001, 0, device_id=1)) == 3  # reference speed >= 1 rpm
        # a refused multi-register write changes nothing (Kv valid, feed-forward mode invalid)
        kv = drive.get_parameter("kv_1000_per_min")
        assert srv.exc(c.write_registers(40373 - 40001, [50, 9], device_id=1)) == 3
        assert drive.get_parameter("positioning_time_ms") != 50 or kv == drive.get_parameter("kv_1000_per_min")
        assert drive.read_object(0x2002, 0) != 9
        # 04: read-only register, writes disabled
        assert srv.exc(c.write_register(40110 - 40001, 1, device_id=1)) == 4
        assert srv.last_error()[:2] == (2, 40110 - 40001)
        assert ro.exc(ro.client.write_register(40361 - 40001, 200, device_id=1)) == 4
        assert ro.last_error()[0] == 1
        # writes disabled: the address is checked first (02 for a register outside the map, FC06 and FC16 alike)
        assert ro.exc(ro.client.write_register(0, 1, device_id=1)) == 2
        assert ro.last_error()[:2] == (7, 0)
        assert ro.exc(ro.client.write_registers(40360 - 40001, [1, 2, 3], device_id=1)) == 4  # all mapped
        assert ro.exc(ro.client.write_registers(40120 - 40001, [0] * 5, device_id=1)) == 2  # crosses a hole
        assert drive.get_parameter("kv_1000_per_min") == kv
        # unknown unit id: gateway target failed to respond
        assert srv.exc(c.read_holding_registers(109, count=1, device_id=9)) == 0x0B
        # FC23: write then read in one request
        r = c.readwrite_registers(read_address=40361 - 40001, read_count=1, write_address=40361 - 40001,
                                  values=[456], device_id=1)
        assert not r.isError() and r.registers == [456]
        assert drive.get_parameter("kv_1000_per_min") == pytest.approx(4.56)
        assert srv.raw(struct.pack(">BHHHHB", 23, 360, 126, 360, 1, 2) + b"\x01\x00") == bytes([0x97, 0x03])
    finally:
        srv.close()
        ro.close()


def test_kv_written_by_modbus_changes_the_following_error_live(server):
    drive = server.links[1].drive
    c = server.client
    assert not c.write_register(40362 - 40001, 0, device_id=1).isError()  # speed precontrol off: FE = v / Kv
    assert not c.write_register(40374 - 40001, 0, device_id=1).isError()
    assert not c.write_register(40361 - 40001, 100, device_id=1).isError()  # Kv = 1 (1000/min)
    assert not c.write_registers(40365 - 40001, [0, 5000], device_id=1).isError()  # FE tolerance 5 mm
    csp_enable(drive)
    v = 0.02  # 1.2 m/min
    x = csp_ramp(drive, v, 1500)
    fe1 = server.read(40114, 2)
    fe1_um = (fe1[0] << 16 | fe1[1])
    assert fe1_um == pytest.approx(1200, rel=0.1)  # Kv = 1: 1 mm per m/min
    assert not c.write_register(40361 - 40001, 300, device_id=1).isError()  # Kv = 3, live
    csp_ramp(drive, v, 1500, x)
    fe3 = server.read(40114, 2)
    fe3_um = (fe3[0] << 16 | fe3[1])
    assert fe3_um == pytest.approx(400, rel=0.1)
    assert drive.get_parameter("kv_1000_per_min") == pytest.approx(3.0)


def test_stw1_runs_the_state_machine_and_bit7_acknowledges_a_fault(server):
    drive = server.links[1].drive
    c = server.client
    assert not c.write_register(40102 - 40001, 8, device_id=1).isError()
    assert not c.write_register(40100 - 40001, 0x047E, device_id=1).isError()
    drive.step(1)
    assert drive.state.cia402_state == "READY TO SWITCH ON"
    assert server.read(40110)[0] & 0b111 == 0b001
    assert not c.write_register(40100 - 40001, 0x047F, device_id=1).isError()
    drive.step(1)
    assert drive.state.cia402_state == "OPERATION ENABLED"
    assert server.read(40110)[0] & 0b111 == 0b111 and server.read(40118) == [4]
    # following error fault: a 5 um window (32-bit write of both words) and a fast target step
    assert not c.write_registers(40365 - 40001, [0, 5], device_id=1).isError()
    assert drive.read_object(0x6065, 0) == 5
    csp_ramp(drive, 0.1, 100)
    for _ in range(50):
        drive.step(1)
    assert drive.state.cia402_state == "FAULT"
    assert server.read(40110)[0] & 0x8 and server.read(40121) == [0x8611] and server.read(40400) == [7452]
    assert not c.write_registers(40365 - 40001, [1, 0x86A0], device_id=1).isError()
    assert not c.write_register(40100 - 40001, 0x04FE, device_id=1).isError()  # acknowledge
    drive.step(1)
    assert drive.state.cia402_state == "SWITCH ON DISABLED"
    assert not server.read(40110)[0] & 0x8


def test_two_axes_one_server_unit_id_is_node_id_and_agrees_with_sdo():
    """Multi-axis: one Modbus server for the runtime's axes; a parameter written by Modbus is what the CANopen
    master reads by SDO, and the other axis is untouched."""
    rig = Rig({1: (seed_config(), 0.0), 2: (seed_config(), 0.01)})
    srv = None
    try:
        drives = {nid: ax.drive for nid, ax in rig.axes.items()}
        srv = Server(drives)
        assert not srv.client.write_register(40361 - 40001, 777, device_id=2).isError()
        assert rig.nodes[2].sdo[0x2000].raw == pytest.approx(7.77, rel=1e-6)
        assert rig.nodes[1].sdo[0x2000].raw != pytest.approx(7.77, rel=1e-6)
        rig.nodes[1].sdo[0x2006].raw = 333  # written by SDO, read by Modbus
        assert srv.read(40368, 2, unit=1) == [0, 333]
        pos = [srv.read(40348, 2, unit=u) for u in (1, 2)]
        assert (pos[1][0] << 16 | pos[1][1]) - (pos[0][0] << 16 | pos[0][1]) == pytest.approx(10000, abs=2)
    finally:
        if srv is not None:
            srv.close()
        rig.close()


def test_reads_are_answered_from_the_published_image_without_serve(server):
    """Valid reads never reach serve's bridge (the drive's process): they come from the shared-memory image,
    which equals the map evaluated on the drive, word for word, and is at most one publication old."""
    from virtualaxis.services.modbus_map import BY_ADDRESS, read_block

    drive = server.links[1].drive
    link = server.links[1]
    csp_enable(drive)
    csp_ramp(drive, 0.05, 200)
    server.svc.sync()
    before = link.requests
    addrs = sorted(BY_ADDRESS)
    image = {}
    for a in addrs:  # one word at a time: any word of the map, halves of 32-bit pairs too
        image[a] = server.client.read_holding_registers(a, count=1, device_id=1).registers[0]
    assert link.requests == before, "a valid read was forwarded to serve"
    assert server.svc.stats()["units"][1]["requests"] == before + len(addrs)
    for a in addrs:  # the drive has not moved since: the image is the map's own evaluation
        assert image[a] == read_block(link, a, 1)[0], f"register {a + 40001}"
    # the drive moves on; without waiting, a read may lag by at most one publication (the period, plus one build)
    csp_ramp(drive, 0.05, 1, x0_m=0.05 * 0.2)
    cycles_now = drive.state.cycles
    w = server.client.read_holding_registers(40376 - 40001, count=2, device_id=1).registers
    assert (w[0] << 16 | w[1]) in (cycles_now - 1, cycles_now)
    server.svc.sync()
    w = server.client.read_holding_registers(40376 - 40001, count=2, device_id=1).registers
    assert (w[0] << 16 | w[1]) == cycles_now


def test_a_publication_longer_than_the_period_leaves_the_drive_lock_to_others(monkeypatch):
    """On a loaded machine an image build can outlast the publication period. The publisher must then rest
    (at least as long as the build took) instead of publishing back to back: the drive's lock is not fair, and a
    publisher that re-takes it at once starves the runtime's cycle and every reader."""
    import virtualaxis.services.register_image as ri

    drive = make_drive()
    link = AxisLink(drive, 1)
    build = ri.build_image

    def slow_build(lk: AxisLink) -> bytes:  # a build twice the period, the drive's lock held throughout
        with lk.drive.lock:
            time.sleep(0.020)
            return build(lk)

    monkeypatch.setattr(ri, "build_image", slow_build)
    publisher = ri.ImagePublisher({1: link}, period_s=0.010).start()
    try:
        builds0 = publisher.builds
        waits = []
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            t0 = time.monotonic()
            with drive.lock:
                pass
            waits.append(time.monotonic() - t0)
            time.sleep(0.002)
        builds = publisher.builds - builds0
    finally:
        publisher.close()
    # 1 s of 20 ms builds each followed by >= 20 ms of rest: at most 25 (back to back would be 50)
    assert 5 <= builds <= 27, f"{builds} publications in 1 s of 20 ms builds"
    assert max(waits) < 0.2, f"the drive's lock was held from a reader for {max(waits) * 1e3:.0f} ms"


def test_an_image_build_and_a_request_never_wait_for_each_other():
    """The register image is built under the drive's lock; a request's view takes the drive's state, which waits
    for that lock. Neither may hold anything the other needs: here a request's view waits for the drive's lock
    while the image build under that lock evaluates a view of its own; the build must finish (a lock shared by
    every view, as ``functools.cached_property`` of Python < 3.12 has, deadlocks it and with it the drive)."""
    import threading

    from virtualaxis.services.modbus_map import View
    from virtualaxis.services.register_image import IMAGE, build_image

    drive = make_drive()
    link = AxisLink(drive, 1)
    held, request_waiting, built = threading.Event(), threading.Event(), []

    def image_build():  # as ImagePublisher: the drive's lock, then views of the map
        with drive.lock:
            held.set()
            request_waiting.wait(5.0)
            time.sleep(0.2)  # the request is now inside its view, waiting for the drive's lock
            built.append(build_image(link))

    def request():
        held.wait(5.0)
        request_waiting.set()
        View(link).s  # noqa: B018 - the state, taken under the drive's lock

    threads = [threading.Thread(target=f, daemon=True) for f in (image_build, request)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(5.0)
    assert not any(t.is_alive() for t in threads), "the image build and a request wait for each other"
    assert len(built) == 1 and len(built[0]) == IMAGE.size


def _eds_limits_read_apart(eds: Path) -> dict[tuple[int, int], tuple[float | None, float | None]]:
    """LowLimit / HighLimit of every object of the EDS, read here from its text (not by the project's code)."""
    import configparser

    p = configparser.RawConfigParser(inline_comment_prefixes=(";",))
    p.optionxform = str
    p.read(eds, encoding="utf-8")
    out = {}
    for section in p.sections():
        name = section.lower()
        if len(name) == 4:
            key = (int(name, 16), 0)
        elif len(name) > 7 and name[4:7] == "sub":
            key = (int(name[:4], 16), int(name[7:], 16))
        else:
            continue
        lo, hi = (p.get(section, k, fallback="").strip() for k in ("LowLimit", "HighLimit"))
        if lo or hi:
            out[key] = (_eds_number(lo), _eds_number(hi))
    return out


def _eds_number(text: str) -> float | None:
    """An EDS limit (decimal, 0x hex or a REAL) as a float; None when empty."""
    if not text:
        return None
    return float(int(text, 0) if text.lstrip("-").isdigit() or text.startswith("0x") else text)


def test_modbus_writes_refuse_what_the_eds_limits_refuse_over_sdo():
    """docs/modbus-map.md: writes are checked exactly like an SDO download of the drive object. For every
    writable register mapped onto an object with an EDS LowLimit / HighLimit, the extreme register values whose
    object value lies beyond a limit are refused with exception 03 (SDO abort 0x06090031 / 0x06090032 in the
    last-error registers) and change nothing; the values inside are taken. (Found by a docs-only client:
    0x200A = 1000 C and 0x2001 = 65.535 were accepted over Modbus while SDO refused them.)"""
    drive = make_drive()
    srv = Server({1: drive}, writable=True)
    limits = _eds_limits_read_apart(ROOT / "eds" / "virtualaxis.eds")
    link = srv.links[1]
    c = srv.client
    refused = taken = 0
    try:
        for reg in REGISTERS:
            w = reg.write
            if not hasattr(w, "index") or (w.index, w.sub) not in limits or reg.dtype not in ("u16", "i16"):
                continue
            lo, hi = limits[(w.index, w.sub)]
            raws = (0, 1, 0x7FFF, 0xFFFF) if reg.dtype == "u16" else (-0x8000, -1, 0, 1, 0x7FFF)
            for raw in raws:
                before = drive.read_object(w.index, w.sub)
                value = w.object_value(link, raw)
                beyond = (hi is not None and value > hi) or (lo is not None and value < lo)
                r = c.write_register(reg.address, raw & 0xFFFF, device_id=1)
                if beyond:
                    assert srv.exc(r) == 3, (reg.number, raw, value)
                    reason, address, abort = srv.last_error()
                    assert address == reg.address and abort == (0x06090031 if hi is not None and value > hi
                                                                 else 0x06090032), (reg.number, raw, hex(abort))
                    assert drive.read_object(w.index, w.sub) == before
                    refused += 1
                elif not r.isError():
                    assert drive.read_object(w.index, w.sub) == pytest.approx(value)
                    taken += 1
        assert refused >= 6 and taken >= 6, (refused, taken)  # 0x2000/01/03/04/0A/0B and option codes at least
    finally:
        srv.close()


def test_modbus_loop_gain_writes_beyond_the_axis_bounds_are_refused():
    """docs/drive.md "Loop-gain bounds": SPEED_KP 40363, KV 40361 and SPEED_TN 40364 beyond the seed axis'
    cascade bounds (speed Kp 21.5 N m s/rad, Kv 37.5 (1000/min), Tn 1.6 ms; inside the EDS ranges) get
    exception 03 with the SDO abort 0x06090031 / 0x06090032 and change nothing; values inside are taken."""
    drive = make_drive()
    srv = Server({1: drive}, writable=True)
    c = srv.client
    try:
        for number, raw, index, abort in ((40363, 30_000, 0x2003, 0x06090031), (40363, 0xFFFF, 0x2003, 0x06090031),
                                          (40361, 4_000, 0x2000, 0x06090031), (40364, 10, 0x2004, 0x06090032)):
            before = drive.read_object(index, 0)
            r = c.write_register(number - 40001, raw, device_id=1)
            assert srv.exc(r) == 3, (number, raw)
            assert srv.last_error()[1:] == (number - 40001, abort), (number, raw)
            assert drive.read_object(index, 0) == before
        for number, raw, index, value in ((40363, 20_000, 0x2003, 20.0), (40361, 3_700, 0x2000, 37.0),
                                          (40364, 17, 0x2004, 1.7), (40364, 0, 0x2004, 0.0)):
            r = c.write_register(number - 40001, raw, device_id=1)
            assert not r.isError(), (number, raw)
            assert drive.read_object(index, 0) == pytest.approx(value)
    finally:
        srv.close()

def test_pipelined_requests_on_one_connection_are_all_answered_in_order(server):
    """The Modbus TCP implementation guide lets a client send several requests on one connection without
    waiting for the answers; pymodbus' own handler answered only one of them (found by a docs-only client).
    Five requests in one TCP segment (FC03 / FC04 / an unknown register / FC03 again) get five answers, in
    order, each with its transaction id and the right content."""
    reqs = [
        (0x101, struct.pack(">BHH", 3, 40110 - 40001, 2)),
        (0x102, struct.pack(">BHH", 4, 40110 - 40001, 1)),
        (0x103, struct.pack(">BHH", 3, 0, 1)),  # no register 40001: exception 02
        (0x104, struct.pack(">BHH", 3, 40361 - 40001, 1)),
        (0x105, struct.pack(">BHH", 3, 40110 - 40001, 12)),
    ]
    server.svc.sync()
    with socket.create_connection(("127.0.0.1", server.port), timeout=3) as s:
        s.sendall(b"".join(struct.pack(">HHHB", tid, 0, len(pdu) + 1, 1) + pdu for tid, pdu in reqs))
        data = b""
        answers = []
        while len(answers) < len(reqs):
            chunk = s.recv(4096)
            assert chunk, f"connection closed after {len(answers)} answers"
            data += chunk
            while len(data) >= 7 and len(data) >= 6 + struct.unpack(">H", data[4:6])[0]:
                n = 6 + struct.unpack(">H", data[4:6])[0]
                answers.append((struct.unpack(">H", data[:2])[0], data[7:n]))
                data = data[n:]
    assert [tid for tid, _ in answers] == [tid for tid, _ in reqs]
    assert answers[0][1][:2] == bytes([3, 4]) and answers[1][1][:2] == bytes([4, 2])
    assert answers[2][1] == bytes([0x83, 0x02])
    assert answers[3][1][:2] == bytes([3, 2]) and answers[4][1][:2] == bytes([3, 24])
    assert answers[1][1][2:4] == answers[0][1][2:4]  # ZSW1 by FC04 = by FC03 (same image)


def test_fc23_refused_read_writes_nothing_fc06_echoes_and_writes_follow_the_position_unit():
    """What a Modbus client that knows only the docs expects:
    - FC23 whose read range is refused (unknown register, a hole) answered exception 02 but had applied its
      write; a refused request must change nothing (docs/side-channels.md). A read-count error names the read
      address in 40496 (was the write address).
    - FC06 must answer with the echo of the request (Modbus application protocol 6.6): STW1 0x047E came back
      as 0x000E, NSOLL_A 0x1000 on a disabled drive as 0x0000.
    - With a position unit of 0.1 um (0x6092:1 = 10 x the lead in um), the um registers were written unscaled
      (4000 um stored 4000 units = 400 um) and FE_TOLERANCE read units as um; NSOLL_A set 0x60FF ten times too
      small."""
    drive = make_drive()
    srv = Server({1: drive})
    try:
        c = srv.client
        kv = drive.read_object(0x2000, 0)
        for read_number, count in ((40103, 1), (40120, 5)):
            r = c.readwrite_registers(read_address=read_number - 40001, read_count=count,
                                      write_address=40361 - 40001, values=[600], device_id=1)
            assert srv.exc(r) == 2
            assert drive.read_object(0x2000, 0) == kv  # nothing written
        assert srv.raw(struct.pack(">BHHHHB", 23, 339, 126, 360, 1, 2) + b"\x02\x58") == bytes([0x97, 0x03])
        assert srv.last_error()[:2] == (8, 339)  # the read's address
        assert drive.read_object(0x2000, 0) == kv
        # FC06 echo
        for number, value in ((40100, 0x047E), (40101, 0x1000), (40361, 555)):
            assert srv.raw(struct.pack(">BHH", 6, number - 40001, value)) == struct.pack(">BHH", 6, number - 40001,
                                                                                          value)
        # 0.1 um position unit
        lead_um = drive.read_object(0x6092, 1)  # 1 unit = 1 um by default: the lead in um
        drive.write_object(0x6092, 0x01, lead_um * 10)
        assert drive.scaling.metres_per_unit == pytest.approx(1e-7)
        for number, index in ((40365, 0x6065), (40368, 0x2006), (40371, 0x6067)):
            assert not c.write_registers(number - 40001, [0, 4000], device_id=1).isError()
            assert drive.read_object(index, 0) == 40_000, hex(index)  # 4000 um = 40000 units of 0.1 um
            assert srv.read(number, 2) == [0, 4000]
        assert not c.write_registers(40365 - 40001, [0xFFFF, 0xFFFF], device_id=1).isError()  # off
        assert drive.read_object(0x6065, 0) == 0xFFFFFFFF and srv.read(40365, 2) == [0xFFFF, 0xFFFF]
        ref_rpm = srv.read(40324)[0]
        assert not c.write_register(40101 - 40001, 0x1000, device_id=1).isError()  # 25 % of the reference
        link = srv.links[1]
        expected_m_s = ref_rpm * 0.25 / link.rpm_per_m_s()
        assert drive.read_object(0x60FF, 0) * 1e-7 == pytest.approx(expected_m_s, rel=1e-3)
        # the documented SINAMICS registers of siemens-conventions.md: 40300 power unit, 40408 / 40409 alarm
        # number / code (40409 was the fault count, 40300 answered exception 02)
        drive.set_warning(0x7320, True)
        assert srv.read(40300) == [0] and srv.read(40408, 2) == [drive.state.alarm_number, 0x7320]
        drive.set_warning(0x7320, False)
        assert srv.read(40408, 2) == [0, 0] and srv.read(40419) == [len(drive.state.faults)]
    finally:
        srv.close()


def test_digital_inputs_register_shows_the_switches_with_a_probe_input_active(server):
    """40356 holds 0x60FD bits 0-15 (the limit and home switches); an active touch probe input (0x60FD bit 16)
    does not saturate it."""
    drive = server.links[1].drive
    drive.write_object(0x2014, 3, 1)  # probe input 1 forced active
    drive.step(2)
    assert drive.read_object(0x60FD, 0) & 0x10000
    assert server.read(40356) == [drive.read_object(0x60FD, 0) & 0xFFFF]
