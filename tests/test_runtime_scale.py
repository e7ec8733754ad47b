"""Issue #15 "Scale": what the serving fast paths must keep.

- lockstep on a host that cannot keep up: every SYNC of a backlog is answered (TPDO, RPDOs applied) but only
  the latest SYNC's cycle runs, the others are counted; ``catch_up_syncs=True`` works the backlog off; a given-up
  SYNC's RPDOs that carry only set-points the next SYNC replaces are left out, a controlword edge never;
- the runtime thread reading a ``udp_multicast`` bus itself (``read_in_loop``): no receive thread, SDO and
  SYNC answered; ``OwnFrameFilteringUdpBus.drain`` takes every waiting datagram, drops the bus's own frames
  and counts one that does not decode;
- the plant's allocation-free step API: ``observe()`` reads what ``state`` reads, and the sensor noise drawn
  ahead in blocks is the same stream as the batch API's, however the two are mixed.
"""

from __future__ import annotations

import os
import socket
import time

import can
import numpy as np
import pytest
from test_drive_rig import seed_config, seed_discrete

from virtualaxis.runtime import AxisNode, Runtime, open_bus
from virtualaxis.sim import AxisSimulator

pytestmark = pytest.mark.exclusive  # timing-sensitive: background jobs stopped meanwhile

_channels = iter(range(1_000_000))


def _sdo_download(master: can.BusABC, rt: Runtime, node: int, index: int, sub: int, value: int, size: int) -> None:
    """Expedited SDO download through the bus, the runtime polled in this thread until the answer."""
    cmd = {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
    data = bytes([cmd, index & 0xFF, index >> 8, sub]) + int(value).to_bytes(4, "little", signed=value < 0)
    master.send(can.Message(arbitration_id=0x600 + node, data=data, is_extended_id=False))
    end = time.monotonic() + 5.0
    while time.monotonic() < end:
        rt.poll_once()
        msg = master.recv(0.002)
        if msg is not None and msg.arbitration_id == 0x580 + node:
            assert msg.data[0] == 0x60, f"SDO 0x{index:04X}:{sub} aborted: {bytes(msg.data).hex()}"
            return
    raise AssertionError(f"no SDO answer for 0x{index:04X}:{sub}")


def _wait_queued(slave, n: int) -> None:
    end = time.monotonic() + 5.0
    while len(slave._queue) < n:
        assert time.monotonic() < end, f"{len(slave._queue)} of {n} frames reached the slave"
        time.sleep(0.001)


def _csp_node_on_virtual_bus(catch_up: bool):
    channel = f"va-scale-{os.getpid()}-{next(_channels)}"
    bus = open_bus(f"virtual:{channel}")
    master = can.Bus(interface="virtual", channel=channel)
    ax = AxisNode(bus, 1, seed_config(), discrete=seed_discrete())
    rt = Runtime(bus, [ax], lockstep=True, catch_up_syncs=catch_up)  # (3 SYNCs > max_sync_backlog 2)
    rt.open()
    master.send(can.Message(arbitration_id=0x000, data=b"\x01\x01", is_extended_id=False))  # NMT start
    _sdo_download(master, rt, 1, 0x1006, 0, 1000, 4)  # 1 ms communication cycle = one drive cycle per SYNC
    _sdo_download(master, rt, 1, 0x1401, 2, 1, 1)  # RPDO2 (CW + target) synchronous
    _sdo_download(master, rt, 1, 0x1801, 2, 1, 1)  # TPDO2 (SW + position) on every SYNC
    _sdo_download(master, rt, 1, 0x6060, 0, 8, 1)  # CSP
    for cw in (0x06, 0x07, 0x0F):
        _sdo_download(master, rt, 1, 0x6040, 0, cw, 2)
    assert ax.drive.cia402_state.name == "OPERATION_ENABLED"
    while master.recv(0.01) is not None:  # the boot-up / heartbeat / TPDO frames so far
        pass
    return bus, master, ax, rt


def _quick_stop_runs_out(drive) -> None:
    """Step the drive until its quick-stop ramp has run out (at most 200 cycles); it ends in SWITCH ON DISABLED
    (quick stop option 0..2)."""
    for _ in range(200):
        if drive.cia402_state.name != "QUICK_STOP_ACTIVE":
            break
        drive.step(1)
    assert drive.cia402_state.name == "SWITCH_ON_DISABLED"


def _backlog(master: can.BusABC, ax: AxisNode, rt: Runtime, targets: list[int],
             controlwords: list[int] | None = None) -> list[can.Message]:
    """Three RPDO2 + SYNC pairs queued before the runtime gets to run, then one pass; the TPDO2s sent."""
    for k, target in enumerate(targets):
        cw = controlwords[k] if controlwords else 0x0F
        data = cw.to_bytes(2, "little") + target.to_bytes(4, "little", signed=True)
        master.send(can.Message(arbitration_id=0x301, data=data, is_extended_id=False))
        master.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
    _wait_queued(ax.slave, 2 * len(targets))
    rt.poll_once()
    frames = []
    while (msg := master.recv(0.05)) is not None:
        frames.append(msg)
    return [f for f in frames if f.arbitration_id == 0x281]


@pytest.mark.parametrize("catch_up", [False, True], ids=["skip", "catch_up"])
def test_lockstep_sync_backlog_answered_once_or_worked_off(catch_up):
    bus, master, ax, rt = _csp_node_on_virtual_bus(catch_up)
    try:
        drive, slave = ax.drive, ax.slave
        cycles0, overruns0 = drive.counters["cycles"], drive.read_object(0x2110, 2)
        rpdos0 = slave.counters["rpdo_received"]
        x0 = drive.read_object(0x6064)
        targets = [x0 + 10, x0 + 20, x0 + 30]
        tpdo2 = _backlog(master, ax, rt, targets)
        assert slave.counters["rpdo_received"] - rpdos0 == 3  # every RPDO of the backlog taken
        assert drive.read_object(0x607A) == targets[-1]
        assert rt.stats.syncs == slave.counters["sync_received"] == 3
        if catch_up:  # one answer and one communication cycle per SYNC, in order
            assert len(tpdo2) == 3
            assert drive.counters["cycles"] - cycles0 == 3
            assert rt.stats.syncs_skipped == slave.counters["syncs_skipped"] == 0
        else:  # every SYNC answered (the master sees no gap), one cycle run; two given up, counted, overruns
            assert len(tpdo2) == 3
            assert len({bytes(f.data) for f in tpdo2}) == 1  # (no cycle between them: the same actual values)
            assert drive.counters["cycles"] - cycles0 == 1
            assert rt.stats.syncs_skipped == slave.counters["syncs_skipped"] == 2
            assert rt.stats.skipped == 2 and drive.read_object(0x2110, 2) - overruns0 == 2
            # the two given up carried only targets that the third replaces: not applied, counted
            assert slave.counters["rpdos_superseded"] == 2
        # the CSP interpolator heads for the latest target: the demand moves toward it
        assert drive._csp.interp.end == pytest.approx(targets[-1] * drive._u)
        # after the backlog the runtime answers every SYNC again; two at once (a short hiccup) are worked off
        tpdo2 = _backlog(master, ax, rt, [targets[-1]])
        assert len(tpdo2) == 1 and rt.stats.syncs_skipped == (0 if catch_up else 2)
        cycles1 = drive.counters["cycles"]
        tpdo2 = _backlog(master, ax, rt, [targets[-1], targets[-1]])
        assert len(tpdo2) == 2 and drive.counters["cycles"] - cycles1 == 2
        assert rt.stats.syncs_skipped == (0 if catch_up else 2)
    finally:
        rt.stop()
        master.shutdown()
        bus.shutdown()


def test_a_controlword_edge_in_a_given_up_sync_is_not_lost():
    """A backlog of three SYNCs on a host that cannot keep up: the first SYNC's RPDO carries a quick stop
    (controlword 0x0B), the other two enable operation again (0x0F). The first SYNC's cycle is given up but its
    RPDO is applied: the quick stop happens (a drive whose 0x605A ends a quick stop in SWITCH ON DISABLED does
    not come back by 0x0F alone). Only the second SYNC's RPDO, which changes nothing but the target the third
    replaces, is left out."""
    bus, master, ax, rt = _csp_node_on_virtual_bus(False)
    try:
        drive, slave = ax.drive, ax.slave
        x0 = drive.read_object(0x6064)
        assert drive.read_object(0x605A) in (0, 1, 2)  # quick stop ends in SWITCH ON DISABLED
        _backlog(master, ax, rt, [x0, x0 + 10, x0 + 20], controlwords=[0x0B, 0x0F, 0x0F])
        assert slave.counters["syncs_skipped"] == 2 and slave.counters["rpdos_superseded"] == 1
        _quick_stop_runs_out(drive)
    finally:
        rt.stop()
        master.shutdown()
        bus.shutdown()


def test_given_up_syncs_from_a_canopen_master_keep_the_quick_stop():
    """The same backlog, but every frame made by the ``canopen`` package's master: RPDO2 packed from its own
    reading of the EDS mapping (``rpdo.read(from_od=True)``), SYNC from its SYNC producer; so the bytes compared
    as "not a set-point" are laid out by another library, not by this stack's packer."""
    import canopen

    from virtualaxis.drive.core import DEFAULT_EDS

    bus, master, ax, rt = _csp_node_on_virtual_bus(False)
    network = canopen.Network(master)  # (it only sends here: no notifier needed)
    try:
        node = network.add_node(1, str(DEFAULT_EDS))
        node.rpdo.read(from_od=True)
        rpdo2 = node.rpdo[2]
        drive, slave = ax.drive, ax.slave
        x0 = drive.read_object(0x6064)
        for cw, target in ((0x0B, x0), (0x0F, x0 + 10), (0x0F, x0 + 20)):
            rpdo2["Controlword"].raw = cw
            rpdo2["Target position"].raw = target
            rpdo2.transmit()
            network.sync.transmit()
        _wait_queued(slave, 6)
        rt.poll_once()
        assert slave.counters["syncs_skipped"] == 2 and slave.counters["rpdos_superseded"] == 1
        assert drive.read_object(0x607A) == x0 + 20
        _quick_stop_runs_out(drive)
    finally:
        rt.stop()
        master.shutdown()
        bus.shutdown()


def _udp_spec() -> tuple[str, int]:
    port = 42000 + (os.getpid() * 7 + next(_channels)) % 3000
    return f"udp_multicast:239.74.163.77,port={port}", port


def test_udp_drain_takes_waiting_frames_drops_own_and_counts_undecodable():
    spec, port = _udp_spec()
    ours = open_bus(spec)
    other = can.Bus(interface="udp_multicast", channel="239.74.163.77", port=port, hop_limit=0)
    raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    raw.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
    try:
        assert ours.drain is not None
        t0 = time.time()
        for i in range(5):
            other.send(can.Message(arbitration_id=0x600 + i, data=bytes([i] * 8), is_extended_id=False))
        ours.send(can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False))  # looped back to us
        # a frame whose data are the packed "channel" key, and a frame of another bus of this process: both
        # foreign (own frames are recognised by the key followed by this bus's own tag)
        other.send(can.Message(arbitration_id=0x605, data=b"\xa7channel", is_extended_id=False))
        sibling = open_bus(spec)
        sibling.send(can.Message(arbitration_id=0x606, data=b"\x06", is_extended_id=False))
        sibling.shutdown()
        raw.sendto(b"\xc1 not msgpack", ("239.74.163.77", port))
        errors: list[Exception] = []
        got: list[can.Message] = []
        end = time.monotonic() + 2.0
        while len(got) < 7 and time.monotonic() < end:
            got += ours.drain(256, errors.append)
            time.sleep(0.01)
        got += ours.drain(256, errors.append)
        assert [m.arbitration_id for m in got] == [0x600 + i for i in range(7)]
        assert [bytes(m.data) for m in got] == [bytes([i] * 8) for i in range(5)] + [b"\xa7channel", b"\x06"]
        assert all(t0 - 0.01 <= m.timestamp <= time.time() + 0.01 for m in got)  # kernel receive time
        assert ours.own_frames_dropped == 1
        assert ours.malformed_dropped == 1 and len(errors) == 1
        assert ours.drain(256) == []  # nothing waits: returns at once
    finally:
        raw.close()
        other.shutdown()
        ours.shutdown()


def test_runtime_reading_the_bus_in_its_own_thread_answers_sdo_and_sync():
    spec, port = _udp_spec()
    bus = open_bus(spec)
    ax = AxisNode(bus, 1, seed_config(), discrete=seed_discrete())
    rt = Runtime(bus, [ax], lockstep=True, read_in_loop=True)
    master = can.Bus(interface="udp_multicast", channel="239.74.163.77", port=port, hop_limit=0)
    try:
        rt.start()
        assert rt._notifier is None  # no receive thread: the runtime thread reads the socket

        def ask(data: bytes, cob: int, answer: int) -> can.Message:
            master.send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))
            end = time.monotonic() + 3.0
            while time.monotonic() < end:
                msg = master.recv(0.05)
                if msg is not None and msg.arbitration_id == answer:
                    return msg
            raise AssertionError(f"no frame 0x{answer:03X}")

        reply = ask(bytes([0x40, 0x00, 0x10, 0, 0, 0, 0, 0]), 0x601, 0x581)  # upload 0x1000 device type
        assert reply.data[0] == 0x43 and int.from_bytes(reply.data[4:8], "little") == 0x00020192
        ask(bytes([0x2F, 0x01, 0x18, 2, 1, 0, 0, 0]), 0x601, 0x581)  # TPDO2 on every SYNC
        master.send(can.Message(arbitration_id=0x000, data=b"\x01\x01", is_extended_id=False))
        cycles0 = ax.drive.counters["cycles"]
        for _ in range(3):
            ask(b"", 0x080, 0x281)  # SYNC -> TPDO2
        assert ax.drive.counters["cycles"] - cycles0 >= 2  # lockstep: the plant advanced on the SYNCs
        assert rt.healthy
    finally:
        rt.stop()
        master.shutdown()
        bus.shutdown()


def test_plant_step_api_observe_and_noise_stream():
    cfg = seed_config().replace(sensors={"position_noise_m": 2e-8, "current_noise_a": 0.01})
    a = AxisSimulator(cfg, seed=7, discrete=seed_discrete())
    b = AxisSimulator(cfg, seed=7, discrete=seed_discrete())
    for sim in (a, b):
        sim.enable(True)
        sim.set_position_setpoint(1e-3, 0.0, 0.0)
    # a: step API (noise drawn 256 cycles ahead) mixed with the batch API; b: the batch API alone, same inputs
    a.advance(300)
    a.run_arrays(np.full(100, 1e-3), np.zeros(100), np.zeros(100), np.zeros(100))
    a.advance(60)
    b.run_arrays(np.full(460, 1e-3), np.zeros(460), np.zeros(460), np.zeros(460))
    assert np.array_equal(a.st, b.st)  # the same noise samples in the same cycles: bit-identical
    reading, state = a.observe(), a.state
    assert a.observe() is reading  # one object, refreshed in place
    for name in state.__dataclass_fields__:
        assert getattr(reading, name) == getattr(state, name), name


def test_poll_once_reads_the_bus_when_the_runtime_reads_it_itself():
    """``poll_once`` (no runtime thread) on a udp_multicast bus read in the loop: the SDO request is taken
    from the socket by the pass itself (there is no receive thread that would have queued it)."""
    spec, port = _udp_spec()
    bus = open_bus(spec)
    ax = AxisNode(bus, 1, seed_config(), discrete=seed_discrete())
    rt = Runtime(bus, [ax], lockstep=True)
    master = can.Bus(interface="udp_multicast", channel="239.74.163.77", port=port, hop_limit=0)
    try:
        rt.open()
        assert rt._notifier is None
        master.send(can.Message(arbitration_id=0x601, data=bytes([0x40, 0x41, 0x60, 0, 0, 0, 0, 0]),
                                is_extended_id=False))
        end = time.monotonic() + 3.0
        reply = None
        while reply is None and time.monotonic() < end:
            rt.poll_once()
            msg = master.recv(0.005)
            if msg is not None and msg.arbitration_id == 0x581:
                reply = msg
        assert reply is not None and reply.data[0] == 0x4B  # statusword, 2 bytes
    finally:
        rt.stop()
        master.shutdown()
        bus.shutdown()
