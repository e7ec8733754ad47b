"""Issue #16 fault injection seen by a real ``canopen`` master in ANOTHER process: ``virtualaxis serve
--allow-fault-injection`` on udp_multicast (hop_limit 0), faults injected over CAN (channel 0x5FF0..0x5FF6 of
drive/injection.py) and by the ``virtualaxis fault`` CLI.

For every fault: the EMCY code and its error-register byte, 0x1001, 0x603F, the CiA 402 state and the reaction
(a stop ramp passes FAULT REACTION ACTIVE before FAULT; an OFF2 fault goes to FAULT at once with the torque
off), a fault reset refused while the cause persists and accepted after the injection is cleared. Without the
flag every write is refused with SDO abort 0x08000022. ``VA_FAULT_TABLE=path`` writes what was measured (the
table in docs/fault-injection.md)."""

from __future__ import annotations

import json
import os
import subprocess
import threading
import time

import can
import canopen
import pytest
from served_drive import CLI, ROOT, served

from virtualaxis.drive.faults import fault_info
from virtualaxis.master import DEFAULT_EDS, connect
from virtualaxis.testing import RemoteInjector

pytestmark = pytest.mark.exclusive  # timing-sensitive: background jobs stopped meanwhile

NODE = 1
MASTER_ID = 0x7E  # the master's heartbeat producer id (0x1016 consumer of the drive)
FAULT_MASK, FAULT, SOD, FRA = 0x4F, 0x08, 0x40, 0x0F


class Frames(can.Listener):
    """EMCY and TPDO1 frames the master sees (monotonic time, cob id, data)."""

    def __init__(self) -> None:
        self.frames: list[tuple[float, int, bytes]] = []
        self._lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        if msg.arbitration_id in (0x80 + NODE, 0x180 + NODE):
            with self._lock:
                self.frames.append((time.monotonic(), msg.arbitration_id, bytes(msg.data)))

    def emcy(self, since: float) -> list[tuple[int, int]]:
        """(code, error register) of the EMCY frames since ``since``."""
        with self._lock:
            return [(int.from_bytes(d[0:2], "little"), d[2]) for t, c, d in self.frames
                    if c == 0x80 + NODE and t >= since]

    def statuswords(self, since: float) -> list[int]:
        with self._lock:
            return [int.from_bytes(d[0:2], "little") for t, c, d in self.frames if c == 0x180 + NODE and t >= since]


class Periodic:
    """A frame sent every ``period_s`` by the master (RPDO stream, heartbeat producer) until stopped."""

    def __init__(self, net: canopen.Network, cob_id: int, data: bytes, period_s: float):
        self._stop = threading.Event()

        def run() -> None:
            while not self._stop.wait(period_s):
                net.send_message(cob_id, data)

        self._thread = threading.Thread(target=run, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(1.0)


def _wait(predicate, timeout: float = 5.0, what: str = "condition"):
    end = time.monotonic() + timeout
    while not (value := predicate()):
        assert time.monotonic() < end, f"{what} not reached in {timeout} s"
        time.sleep(0.005)
    return value


def _sw(node) -> int:
    return node.sdo[0x6041].raw


def _reset(node) -> None:
    node.sdo[0x6040].raw = 0x00
    node.sdo[0x6040].raw = 0x80


def _enable(node, mode: int) -> None:
    _reset(node)
    node.sdo[0x6060].raw = mode
    node.sdo[0x60FF].raw = 0
    for cw, expect in ((0x06, 0x21), (0x07, 0x23), (0x0F, 0x27)):
        node.sdo[0x6040].raw = cw
        _wait(lambda e=expect: _sw(node) & 0x6F == e, what=f"state {expect:#x} (statusword {_sw(node):#06x})")


def _run_pv(node, velocity_units_s: int) -> None:
    """Fault reset, PV mode, enable, run at ``velocity_units_s`` (1 unit = 1 um)."""
    _enable(node, 3)
    node.sdo[0x60FF].raw = velocity_units_s
    _wait(lambda: abs(node.sdo[0x606C].raw - velocity_units_s) < abs(velocity_units_s) * 0.05 + 500,
          what="velocity reached")


def _start_pp(node, distance_units: int, velocity_units_s: int) -> None:
    """Fault reset, PP mode, enable, a relative move commanded (position control)."""
    _enable(node, 1)
    node.sdo[0x6081].raw = velocity_units_s
    node.sdo[0x607A].raw = distance_units
    node.sdo[0x6040].raw = 0x5F  # new set-point, relative
    node.sdo[0x6040].raw = 0x4F


def _run_pp(node, distance_units: int, velocity_units_s: int) -> None:
    """:func:`_start_pp`, then wait until the move is under way."""
    _start_pp(node, distance_units, velocity_units_s)
    _wait(lambda: abs(node.sdo[0x606C].raw) > velocity_units_s * 0.5, what="PP move under way")


def _expect_fault(node, frames: Frames, code: int, since: float, *, ramp: bool, timeout: float = 5.0) -> dict:
    """EMCY ``code``, FAULT; the reaction from the statusword sequence (TPDO1 + SDO polls since ``since``)."""
    bits = fault_info(code).register_bits | 0x01
    polled: list[int] = []

    def faulted() -> bool:
        sw = _sw(node)
        polled.append(sw)
        return sw & FAULT_MASK == FAULT and any(c == code for c, _ in frames.emcy(since))

    _wait(faulted, timeout, f"EMCY {code:#06x} and FAULT")
    emcy = [e for e in frames.emcy(since) if e[0] == code]
    sws = frames.statuswords(since) + polled
    seen = {
        "emcy": f"0x{emcy[0][0]:04X}",
        "emcy_error_register": f"0x{emcy[0][1]:02X}",
        "0x1001": f"0x{node.sdo[0x1001].raw:02X}",
        "0x603F": f"0x{node.sdo[0x603F].raw:04X}",
        "fault_reaction_active_seen": any(sw & FAULT_MASK == FRA for sw in sws),
    }
    assert node.sdo[0x603F].raw == code, seen
    assert emcy[0][1] == bits, seen  # generic bit 0 + the code's class bit
    assert node.sdo[0x1001].raw & bits == bits, seen
    if ramp:
        assert seen["fault_reaction_active_seen"], seen
    else:  # OFF2: pulses off at once, straight to FAULT (no fault reaction ramp), no torque
        assert not seen["fault_reaction_active_seen"], seen
        _wait(lambda: abs(node.sdo[0x6077].raw) <= 10, 0.5, "torque off (<= 1 % of rated)")
    return seen


def _reset_refused(node) -> bool:
    _reset(node)
    time.sleep(0.05)
    return _sw(node) & FAULT_MASK == FAULT


def _reset_accepted_after(node, clear, what: str, timeout: float = 5.0) -> float:
    """Run ``clear`` and wait for a fault reset to be accepted; returns the time it took [s]."""
    t = time.monotonic()
    clear()

    def ok() -> bool:
        _reset(node)
        time.sleep(0.01)
        return _sw(node) & FAULT_MASK == SOD

    _wait(ok, timeout, f"{what}: fault reset accepted after clearing")
    return time.monotonic() - t


def _master(spec: str):
    net = connect(spec)
    frames = Frames()
    net.notifier.add_listener(frames)
    node = canopen.BaseNode402(NODE, DEFAULT_EDS)
    node.sdo.RESPONSE_TIMEOUT = 2.0
    net.add_node(node)
    node.nmt.state = "OPERATIONAL"
    return net, node, frames


def test_every_fault_across_processes():
    """All faults on one served drive (0x6007 = 1 fault, 0x605E = 2 quick-stop ramp, ramps 0.5 m/s^2 so that a
    master polling by SDO sees FAULT REACTION ACTIVE)."""
    with served("--duration", "200", "--allow-fault-injection") as s:
        net, node, frames = _master(s.spec)
        inj = RemoteInjector(node)
        measured: dict[str, dict] = {}
        try:
            for index, value in ((0x6007, 1), (0x605E, 2), (0x6083, 2_000_000), (0x6084, 500_000),
                                 (0x6085, 500_000)):
                node.sdo[index].raw = value
            # device faults with a persistent cause: OFF2 / 0x605E ramp; reset refused until cleared
            for kind, code, ramp in (("encoder_loss", 0x7305, False), ("dc_link_undervoltage", 0x3220, True),
                                     ("dc_link_overvoltage", 0x3210, True)):
                _run_pv(node, 50_000)
                t = time.monotonic()
                inj.inject(kind)
                measured[kind] = _expect_fault(node, frames, code, t, ramp=ramp)
                measured[kind]["reset_refused_while_injected"] = _reset_refused(node)
                assert measured[kind]["reset_refused_while_injected"], kind
                _reset_accepted_after(node, lambda k=kind: inj.clear(k), kind)
                assert kind not in inj.active
            # over-current: a trip (OFF2); the trip itself is the cause: a reset is accepted at once
            _run_pv(node, 50_000)
            t = time.monotonic()
            inj.inject("over_current")
            measured["over_current"] = _expect_fault(node, frames, 0x2310, t, ramp=False)
            measured["over_current"]["reset_refused_while_injected"] = _reset_refused(node)
            _reset_accepted_after(node, lambda: inj.clear("over_current"), "over_current")
            # limit switch plus while moving toward it: OFF3; the reset is accepted on the switch (drive off it)
            for side, velocity, code in ((+1, 50_000, 0xFF11), (-1, -50_000, 0xFF10)):
                _run_pv(node, velocity)
                t = time.monotonic()
                inj.inject("limit_switch", magnitude=side)
                key = f"limit_switch {'plus' if side > 0 else 'minus'}"
                measured[key] = _expect_fault(node, frames, code, t, ramp=True)
                measured[key]["reset_refused_while_injected"] = _reset_refused(node)
                _reset_accepted_after(node, lambda: inj.clear("limit_switch"), key)
            # following error: a brake on the table during a PP move; the drive's FE monitor trips (0x605E ramp)
            _run_pp(node, 200_000, 50_000)
            t = time.monotonic()
            inj.inject("following_error")
            measured["following_error"] = _expect_fault(node, frames, 0x8611, t, ramp=True)
            # at rest the following error is gone: the reset is accepted with the brake still on; the next move
            # trips again (a drive cannot see the brake)
            measured["following_error"]["reset_refused_while_injected"] = _reset_refused(node)
            assert not measured["following_error"]["reset_refused_while_injected"]
            t = time.monotonic()
            _start_pp(node, 200_000, 50_000)
            _expect_fault(node, frames, 0x8611, t, ramp=True)
            _reset_accepted_after(node, lambda: inj.clear("following_error"), "following_error")
            # motor over-temperature ramp: warning first (bit 7, 0x2031 = 7910, still enabled), then the fault;
            # a reset is refused until the winding model has cooled below 0x200B
            _run_pv(node, 20_000)
            temp = node.sdo[0x2020].raw
            node.sdo[0x200A].raw = temp + 2.0
            node.sdo[0x200B].raw = temp + 4.0
            t = time.monotonic()
            inj.inject("motor_overtemperature")
            _wait(lambda: _sw(node) & 0x80, 5, "warning bit 7")
            warned = _sw(node)
            assert warned & 0x6F == 0x27 and node.sdo[0x2031].raw == 7910, hex(warned)
            measured["motor_overtemperature"] = _expect_fault(node, frames, 0x4310, t, ramp=True)
            measured["motor_overtemperature"]["warning_before_fault"] = f"statusword 0x{warned:04X}, 0x2031 = 7910"
            assert node.sdo[0x2020].raw >= temp + 4.0 - 0.1
            inj.clear("motor_overtemperature")
            measured["motor_overtemperature"]["reset_refused_while_hot"] = _reset_refused(node)
            assert measured["motor_overtemperature"]["reset_refused_while_hot"]
            node.sdo[0x200B].raw = 145.0  # the winding cools slowly (600 s time constant): raise the threshold
            node.sdo[0x200A].raw = 130.0
            _reset_accepted_after(node, lambda: None, "motor_overtemperature")
            # lost RPDOs: RPDO1 (controlword) every 10 ms with a 60 ms deadline (0x1400:5); the frames are dropped
            _run_pv(node, 50_000)
            node.sdo[0x1400][5].raw = 60
            stream = Periodic(net, 0x200 + NODE, bytes([0x0F, 0x00]), 0.01)
            try:
                time.sleep(0.1)
                t = time.monotonic()
                inj.inject("lost_rpdos")
                measured["lost_rpdos"] = _expect_fault(node, frames, 0x8250, t, ramp=True)
                measured["lost_rpdos"]["reset_refused_while_injected"] = _reset_refused(node)  # recorded
                _reset_accepted_after(node, lambda: inj.clear("lost_rpdos"), "lost_rpdos")
            finally:
                stream.stop()
                node.sdo[0x1400][5].raw = 0
            # master heartbeat loss: consumer 0x1016:1 = master, 100 ms; the producer runs every 20 ms
            _run_pv(node, 50_000)
            heartbeat = Periodic(net, 0x700 + MASTER_ID, bytes([0x05]), 0.02)
            try:
                node.sdo[0x1016][1].raw = (MASTER_ID << 16) | 100
                time.sleep(0.1)
                t = time.monotonic()
                inj.inject("heartbeat_loss")
                measured["heartbeat_loss"] = _expect_fault(node, frames, 0x8130, t, ramp=True)
                measured["heartbeat_loss"]["reset_refused_while_injected"] = _reset_refused(node)  # recorded
                _reset_accepted_after(node, lambda: inj.clear("heartbeat_loss"), "heartbeat_loss")
            finally:
                node.sdo[0x1016][1].raw = 0
                heartbeat.stop()
            node.nmt.state = "OPERATIONAL"  # 0x1029 error behaviour may have switched the node to pre-operational
            # bus-off, intermittent (50 % of 400 ms): deaf and mute while off; on recovery EMCY 0x8140 + 0x6007
            _run_pv(node, 50_000)
            t = time.monotonic()
            inj.inject("bus_off", duty=0.5, period_s=0.4)
            _wait(lambda: any(c == 0x8140 for c, _ in frames.emcy(t)), 5, "EMCY 0x8140 on recovery from bus-off")
            _wait(lambda: _try(lambda: inj.clear("bus_off")), 5, "clear bus_off between its on-phases")
            _wait(lambda: _sw(node) & FAULT_MASK == FAULT, 3, "FAULT after bus-off")
            emcy = [e for e in frames.emcy(t) if e[0] == 0x8140]
            sws = frames.statuswords(t)
            measured["bus_off (intermittent 50 % of 400 ms)"] = seen = {
                "emcy": "0x8140", "emcy_error_register": f"0x{emcy[0][1]:02X}",
                "0x1001": f"0x{node.sdo[0x1001].raw:02X}", "0x603F": f"0x{node.sdo[0x603F].raw:04X}",
                "fault_reaction_active_seen": any(sw & FAULT_MASK == FRA for sw in sws)}
            assert emcy[0][1] == 0x11 and node.sdo[0x603F].raw == 0x8140, seen
            assert seen["fault_reaction_active_seen"], (seen, [hex(x) for x in sws])
            _reset_accepted_after(node, lambda: None, "bus_off")
            # intermittent encoder loss: 50 % of 200 ms -> a new fault (EMCY) at every on-phase
            _run_pv(node, 20_000)
            t = time.monotonic()
            inj.inject("encoder_loss", duty=0.5, period_s=0.2)
            time.sleep(0.9)
            n = sum(1 for c, _ in frames.emcy(t) if c == 0x7305)
            assert n >= 3, frames.emcy(t)
            _reset_accepted_after(node, inj.clear, "intermittent encoder_loss")
            assert inj.active == []
            measured["encoder_loss (intermittent 50 % of 200 ms)"] = {"emcy_0x7305_in_0.9_s": n}
            # the CLI on this drive
            cli = subprocess.run([*CLI, "fault", "--can", s.spec, "--node-id", str(NODE), "inject", "over_current"],
                                 capture_output=True, text=True, timeout=60, cwd=ROOT)
            assert cli.returncode == 0, cli.stderr
            _wait(lambda: node.sdo[0x603F].raw == 0x2310, 3, "CLI-injected over_current")
            cli = subprocess.run([*CLI, "fault", "--can", s.spec, "--node-id", str(NODE), "clear"],
                                 capture_output=True, text=True, timeout=60, cwd=ROOT)
            assert cli.returncode == 0 and "active: none" in cli.stdout, (cli.stdout, cli.stderr)
            cli = subprocess.run([*CLI, "fault", "--can", s.spec, "--node-id", str(NODE), "list"],
                                 capture_output=True, text=True, timeout=60, cwd=ROOT)
            assert cli.returncode == 0 and "encoder_loss" in cli.stdout and "0x7305" in cli.stdout, cli.stderr
        finally:
            net.disconnect()
        out = os.environ.get("VA_FAULT_TABLE")
        if out:
            with open(out, "w") as f:
                json.dump(measured, f, indent=1)
    assert s.returncode == 0, s.stderr[-2000:]


def _try(fn) -> bool:
    try:
        fn()
        return True
    except (canopen.SdoCommunicationError, canopen.SdoAbortedError):
        return False


def test_injection_refused_without_the_flag():
    """Without --allow-fault-injection: SDO abort 0x08000022 on inject and clear, the CLI says how to allow it
    (exit 2, no traceback), the drive stays fault free; reading the objects (EDS) still works."""
    with served("--duration", "60") as s:
        net, node, _frames = _master(s.spec)
        try:
            inj = RemoteInjector(node)
            for call in (lambda: inj.inject("encoder_loss"), lambda: inj.clear("encoder_loss")):
                with pytest.raises(canopen.SdoAbortedError) as err:
                    call()
                assert err.value.code == 0x08000022
            assert inj.active == [] and node.sdo[0x5FF6].raw == 0
            with pytest.raises(canopen.SdoAbortedError) as err:  # the drive's own injection object is gated too
                node.sdo[0x2010].raw = 0x4210
            assert err.value.code == 0x08000022
            cli = subprocess.run([*CLI, "fault", "--can", s.spec, "--node-id", str(NODE), "inject", "over_current"],
                                 capture_output=True, text=True, timeout=60, cwd=ROOT)
            assert cli.returncode == 2 and "--allow-fault-injection" in cli.stderr, cli.stderr
            assert "Traceback" not in cli.stderr and cli.stderr.count("08000022") == 1, cli.stderr
            assert node.sdo[0x603F].raw == 0 and _sw(node) & FAULT_MASK != FAULT
        finally:
            net.disconnect()
    assert s.returncode == 0, s.stderr[-2000:]


@pytest.mark.parametrize("kind", ["encoder_loss", "dc_link_undervoltage"])
def test_a_persistent_cause_faults_the_drive_again_after_an_nmt_reset_node(kind):
    """A real drive whose encoder is still unplugged faults again right after a power-on reset: NMT Reset Node
    restarts the drive (fault buffer cleared), the injected cause persists, and the drive is back in FAULT with
    its EMCY code in 0x603F; it cannot be enabled until the injection is cleared."""
    code = 0x7305 if kind == "encoder_loss" else 0x3220
    with served("--allow-fault-injection") as s:
        net = connect(s.spec)
        try:
            node = canopen.BaseNode402(NODE, str(DEFAULT_EDS))
            node.sdo.RESPONSE_TIMEOUT = 2.0
            net.add_node(node)
            inj = RemoteInjector(node)
            inj.inject(kind)
            _wait(lambda: node.sdo[0x6041].raw & FAULT_MASK == FAULT)
            net.send_message(0x000, bytes((0x81, NODE)))  # NMT reset node
            time.sleep(0.5)
            _wait(lambda: node.sdo[0x6041].raw & FAULT_MASK == FAULT and node.sdo[0x603F].raw == code)
            assert inj.active == [kind]
            for cw in (0x80, 0x00, 0x06, 0x07, 0x0F):  # a fault reset is refused while the cause persists
                node.sdo[0x6040].raw = cw
                time.sleep(0.02)
            assert node.sdo[0x6041].raw & FAULT_MASK == FAULT
            inj.clear(kind)
            node.sdo[0x6040].raw = 0x80
            _wait(lambda: node.sdo[0x6041].raw & FAULT_MASK == SOD)
        finally:
            net.disconnect()

