"""PDO engine through a real canopen master: SYNC-driven, event-driven and timer TPDOs with inhibit time,
SYNC counter and start value, synchronous window, RPDOs writing the dictionary (asynchronous at once,
synchronous at the next SYNC), RPDO length errors and deadlines, dynamic remapping with the COB-ID bit 31
protocol and its aborts, NMT-state gating."""

from __future__ import annotations

import struct
import threading
import time

import canopen
import pytest

from virtualaxis.canopen_slave import errors as ab
from virtualaxis.canopen_slave.testing import MasterRig, RecordingApp
from virtualaxis.canopen_slave.testing import wait_until as _wait_until

NODE = 11
TPDO1, TPDO2, TPDO3, TPDO4 = (0x180 + NODE, 0x280 + NODE, 0x380 + NODE, 0x480 + NODE)
EMCY = 0x80 + NODE


def count_position(slave, _counter, _now):
    """Test application cycle: the position actual value moves by one increment per SYNC."""
    slave.write(0x6064, 0, slave.read(0x6064) + 1)


@pytest.fixture
def rig():
    app = RecordingApp()
    sync_counters: list[int] = []

    def cycle(slave, counter, now):
        sync_counters.append(counter)
        count_position(slave, counter, now)

    with MasterRig(NODE, app=app, on_cycle=cycle) as r:
        app.slave = r.slave
        r.app = app
        r.sync_counters = sync_counters
        yield r


def wait_until(predicate, timeout_s: float = 2.0) -> bool:
    return _wait_until(predicate, timeout_s, poll_s=0.002)


def operational(rig):
    rig.node.nmt.state = "OPERATIONAL"
    assert wait_until(lambda: int(rig.slave.nmt_state) == 5)


def sync(rig, n: int = 1, counter: int | None = None) -> None:
    """Send n SYNC frames, each after the slave handled the previous one."""
    for _ in range(n):
        before = rig.slave.counters["sync_received"]
        rig.send(0x80, b"" if counter is None else bytes((counter,)))
        assert wait_until(lambda b=before: rig.slave.counters["sync_received"] > b and
                          len(rig.sync_counters) > 0)
        time.sleep(0.003)


def sdo_abort(fn, *args) -> int:
    with pytest.raises(canopen.SdoAbortedError) as info:
        fn(*args)
    return info.value.code


def test_synchronous_tpdos_every_nth_sync(rig):
    sdo = rig.node.sdo
    sdo[0x1802][2].raw = 2                                  # TPDO3 every 2nd SYNC
    sdo[0x1802][1].raw = 0x40000380 + NODE                  # ... and valid
    operational(rig)
    rig.sniffer.clear()
    sync(rig, 10)
    assert wait_until(lambda: len(rig.sniffer.of(TPDO2)) == 10)
    time.sleep(0.02)
    assert len(rig.sniffer.of(TPDO2)) == 10
    assert len(rig.sniffer.of(TPDO3)) == 5
    positions = [struct.unpack_from("<i", d, 2)[0] for _t, d in rig.sniffer.of(TPDO2)]
    assert positions == list(range(positions[0], positions[0] + 10))   # value of this SYNC's cycle


def test_sync_counter_and_sync_start_value(rig):
    sdo = rig.node.sdo
    sdo[0x1019].raw = 10
    sdo[0x1801][2].raw = 2
    sdo[0x1801][6].raw = 3
    assert sdo_abort(sdo.download, 0x1019, 0, b"\x01") == ab.INVALID_VALUE
    sdo[0x1006].raw = 1000
    assert sdo_abort(sdo.download, 0x1019, 0, b"\x05") == ab.DEVICE_STATE
    operational(rig)
    rig.sniffer.clear()
    rig.sync_counters.clear()
    for c in range(1, 11):
        sync(rig, 1, counter=c)
    assert rig.sync_counters == list(range(1, 11))
    time.sleep(0.02)
    # SYNC 3 counts as the first: TPDO2 (type 2) at SYNC 4, 6, 8, 10
    assert len(rig.sniffer.of(TPDO2)) == 4
    # a SYNC without its counter is a length error: EMCY 0x8240, not a SYNC
    rig.send(0x80, b"")
    assert rig.sniffer.wait_for(EMCY, match=lambda d: d[:2] == b"\x40\x82")
    assert rig.slave.counters["sync_length_errors"] == 1
    assert rig.sync_counters == list(range(1, 11))


def test_synchronous_window_drops_late_tpdos(rig):
    sdo = rig.node.sdo
    operational(rig)
    sync(rig, 2)
    assert wait_until(lambda: len(rig.sniffer.of(TPDO2)) == 2)
    sdo[0x1007].raw = 500                                     # 500 us window
    rig.runner.on_cycle = lambda s, c, n: (rig.sync_counters.append(c), time.sleep(0.003))
    rig.sniffer.clear()
    sync(rig, 3)
    time.sleep(0.02)
    assert rig.sniffer.of(TPDO2) == []
    sdo[0x1007].raw = 0
    sync(rig, 1)
    assert wait_until(lambda: len(rig.sniffer.of(TPDO2)) == 1)


def test_event_driven_tpdo_inhibit_time_and_event_timer(rig):
    sdo = rig.node.sdo
    sdo[0x1800][1].raw = 0xC0000180 + NODE                   # invalid, to change the inhibit time
    sdo[0x1800][3].raw = 200                                 # 20 ms
    sdo[0x1800][5].raw = 0                                   # no event timer for the first part
    sdo[0x1800][1].raw = 0x40000180 + NODE
    operational(rig)
    stop = threading.Event()

    def change_statusword():
        i = 0
        while not stop.is_set():
            i += 1
            rig.runner.call(rig.slave.write, 0x6041, 0, i & 0xFFFF)
            time.sleep(0.001)

    rig.sniffer.clear()
    thread = threading.Thread(target=change_statusword)
    thread.start()
    time.sleep(0.3)
    stop.set()
    thread.join()
    times = [t for t, _d in rig.sniffer.of(TPDO1)]
    gaps = [b - a for a, b in zip(times, times[1:], strict=False)]
    assert 3 <= len(times) <= 0.3 / 0.020 + 2
    assert min(gaps) > 0.015                                 # inhibit time 20 ms (receive jitter allowed)
    # event timer 100 ms without any change
    sdo[0x1800][5].raw = 100
    time.sleep(0.05)
    rig.sniffer.clear()
    time.sleep(0.55)
    times = [t for t, _d in rig.sniffer.of(TPDO1)]
    assert 4 <= len(times) <= 7
    assert min(b - a for a, b in zip(times, times[1:], strict=False)) > 0.08


def test_nothing_is_sent_or_received_outside_operational(rig):
    node = rig.node
    rig.sniffer.clear()
    sync(rig, 3)
    rig.send(0x200 + NODE, b"\x0f\x00")
    time.sleep(0.25)
    assert all(rig.sniffer.of(c) == [] for c in (TPDO1, TPDO2, TPDO3, TPDO4))
    assert rig.slave.read(0x6040) == 0
    assert rig.slave.counters["pdo_ignored_nmt_state"] == 1
    node.nmt.state = "STOPPED"
    rig.send(0x200 + NODE, b"\x0f\x00")
    sync(rig, 2)
    time.sleep(0.15)
    assert all(rig.sniffer.of(c) == [] for c in (TPDO1, TPDO2, TPDO3, TPDO4))
    assert rig.slave.read(0x6040) == 0


def test_rpdo_writes_the_dictionary(rig):
    node = rig.node
    node.rpdo.read()
    operational(rig)
    node.rpdo[1]["Controlword"].raw = 0x000F
    node.rpdo[1].transmit()
    assert wait_until(lambda: rig.slave.read(0x6040) == 0x0F)
    assert node.sdo[0x6040].raw == 0x0F
    assert (0x6040, 0, 0x0F) in rig.app.writes
    # modes of operation through RPDO4: supported mode applied, unsupported refused by the application
    node.rpdo[4]["Modes of operation"].raw = 9
    node.rpdo[4].transmit()
    assert wait_until(lambda: rig.slave.read(0x6061) == 9)
    node.rpdo[4]["Modes of operation"].raw = 2
    node.rpdo[4].transmit()
    assert wait_until(lambda: rig.slave.counters["rpdo_values_refused"] == 1)
    assert rig.slave.read(0x6060) == 9


def test_synchronous_rpdo_takes_effect_at_the_next_sync(rig):
    node = rig.node
    node.rpdo.read()
    node.rpdo[2].trans_type = 1
    node.rpdo[2].save()
    operational(rig)
    node.rpdo[2]["Target position"].raw = 123456
    node.rpdo[2].transmit()
    time.sleep(0.05)
    assert node.sdo[0x607A].raw == 0
    sync(rig, 1)
    assert wait_until(lambda: rig.slave.read(0x607A) == 123456)
    assert node.sdo[0x607A].raw == 123456


def test_dynamic_remapping_with_the_canopen_master(rig):
    node = rig.node
    node.tpdo.read()
    node.rpdo.read()
    tpdo = node.tpdo[4]
    tpdo.clear()
    tpdo.add_variable(0x6064)
    tpdo.add_variable(0x6041)
    tpdo.add_variable(0x6061)
    tpdo.trans_type = 1
    tpdo.enabled = True
    tpdo.save()
    rpdo = node.rpdo[3]
    rpdo.clear()
    rpdo.add_variable(0x607A)
    rpdo.add_variable(0x6081)
    rpdo.enabled = True
    rpdo.save()
    assert node.sdo[0x1A03][0].raw == 3 and node.sdo[0x1603][0].raw == 2
    rig.slave.write(0x6041, 0, 0x1237)
    operational(rig)
    rpdo["Target position"].raw = -5
    rpdo["Profile velocity"].raw = 4000
    rpdo.transmit()
    assert wait_until(lambda: rig.slave.read(0x6081) == 4000)
    assert rig.slave.read(0x607A) == -5
    rig.sniffer.clear()
    sync(rig, 1)
    frames = rig.sniffer.wait_for(TPDO4)
    assert len(frames[0][1]) == 7
    position, statusword, mode = struct.unpack("<iHb", frames[0][1])
    assert statusword == 0x1237 and position == rig.slave.read(0x6064)


def test_remapping_protocol_aborts(rig):
    sdo = rig.node.sdo
    assert sdo_abort(sdo.download, 0x1A01, 0, b"\x00") == ab.DEVICE_STATE          # PDO valid
    assert sdo_abort(sdo.download, 0x1801, 1, struct.pack("<I", 0x300 + NODE)) == ab.INVALID_VALUE
    assert sdo_abort(sdo.download, 0x1801, 3, b"\x0a\x00") == ab.INVALID_VALUE     # inhibit while valid
    sdo.download(0x1801, 1, struct.pack("<I", 0xC0000280 + NODE))                  # bit 31: invalid
    assert sdo_abort(sdo.download, 0x1A01, 1, struct.pack("<I", 0x60640020)) == ab.DEVICE_STATE  # sub0 != 0
    sdo.download(0x1A01, 0, b"\x00")
    assert sdo_abort(sdo.download, 0x1A01, 1, struct.pack("<I", 0x10000020)) == ab.NOT_MAPPABLE
    assert sdo_abort(sdo.download, 0x1A01, 1, struct.pack("<I", 0x20000020)) == ab.NOT_MAPPABLE  # REAL32, no
    assert sdo_abort(sdo.download, 0x1A01, 1, struct.pack("<I", 0x12340020)) == ab.NOT_MAPPABLE  # no object
    for sub, obj in ((1, 0x60640020), (2, 0x606C0020), (3, 0x60F40020)):
        sdo.download(0x1A01, sub, struct.pack("<I", obj))
    assert sdo_abort(sdo.download, 0x1A01, 0, b"\x03") == ab.MAPPING_TOO_LONG
    assert sdo_abort(sdo.download, 0x1A01, 0, b"\x09") == ab.VALUE_TOO_HIGH
    sdo.download(0x1A01, 0, b"\x02")
    assert sdo_abort(sdo.download, 0x1801, 1, struct.pack("<I", 0x581)) == ab.INVALID_VALUE    # restricted
    assert sdo_abort(sdo.download, 0x1801, 1, struct.pack("<I", 0xA0000280)) == ab.INVALID_VALUE  # 29-bit
    sdo.download(0x1801, 1, struct.pack("<I", 0x380 + NODE + 0x10))                # valid, new COB-ID
    sdo.download(0x1400, 1, struct.pack("<I", 0x80000200 + NODE))
    assert sdo_abort(sdo.download, 0x1600, 1, struct.pack("<I", 0x60410010)) == ab.DEVICE_STATE
    sdo.download(0x1600, 0, b"\x00")
    assert sdo_abort(sdo.download, 0x1600, 1, struct.pack("<I", 0x60410010)) == ab.NOT_MAPPABLE  # ro in RPDO
    assert sdo_abort(sdo.download, 0x1401, 1, struct.pack("<I", 0x300 + NODE + 1)) == ab.INVALID_VALUE
    operational(rig)
    sync(rig, 1)
    frames = rig.sniffer.wait_for(0x390 + NODE)
    assert len(frames[0][1]) == 8


def test_rpdo_length_errors(rig):
    operational(rig)
    rig.send(0x300 + NODE, b"\x01")                                  # RPDO2 maps 6 bytes
    assert rig.sniffer.wait_for(EMCY, match=lambda d: d[:2] == b"\x10\x82")
    assert wait_until(lambda: ("rpdo_length", 2) in rig.app.errors)
    rig.send(0x200 + NODE, b"\x06\x00\xff")                           # RPDO1 maps 2: too long, used
    assert rig.sniffer.wait_for(EMCY, match=lambda d: d[:2] == b"\x20\x82")
    assert wait_until(lambda: rig.slave.read(0x6040) == 6)
    assert rig.slave.counters["rpdo_length_errors"] == 2
    assert rig.node.sdo[0x1003][0].raw == 2


def test_rpdo_deadline_monitoring(rig):
    rig.node.sdo[0x1400][5].raw = 50
    operational(rig)
    rig.send(0x200 + NODE, b"\x06\x00")
    assert rig.sniffer.wait_for(EMCY, match=lambda d: d[:2] == b"\x50\x82", timeout_s=1.0)
    assert wait_until(lambda: rig.app.errors == [("rpdo_timeout", 1)])
    assert rig.slave.counters["rpdo_timeouts"] == 1


def test_sync_rpdo_order_in_the_application_cycle(rig):
    """Contract order: the cycle of SYNC n sees the RPDO sent before SYNC n only after on_sync (one cycle
    later); apply_sync_rpdos() before the cycle makes it visible in the cycle of SYNC n."""
    node = rig.node
    seen: list[int] = []
    ahead = {"on": False}

    def cycle(slave, counter, _now):
        rig.sync_counters.append(counter)
        if ahead["on"]:
            slave.apply_sync_rpdos()
        seen.append(slave.read(0x607A))

    rig.runner.on_cycle = cycle
    node.rpdo.read()
    node.rpdo[2].trans_type = 1
    node.rpdo[2].save()
    operational(rig)
    node.rpdo[2]["Target position"].raw = 77
    node.rpdo[2].transmit()
    time.sleep(0.03)
    sync(rig, 1)
    assert seen[-1] == 0 and wait_until(lambda: rig.slave.read(0x607A) == 77)
    ahead["on"] = True
    node.rpdo[2]["Target position"].raw = 88
    node.rpdo[2].transmit()
    time.sleep(0.03)
    sync(rig, 1)
    assert seen[-1] == 88
    sync(rig, 1)                                  # no new RPDO: nothing pending, value kept
    assert seen[-1] == 88 and rig.slave.read(0x607A) == 88


def test_acyclic_synchronous_tpdo_and_moved_sync_cob_id(rig):
    sdo = rig.node.sdo
    sdo[0x1801][2].raw = 0                                   # TPDO2: at a SYNC, only after a change
    sdo[0x1005].raw = 0x90                                   # SYNC now on 0x090
    assert sdo_abort(sdo.download, 0x1005, 0, struct.pack("<I", 0x40000080)) == ab.INVALID_VALUE  # producer
    rig.runner.on_cycle = lambda s, c, n: rig.sync_counters.append(c)     # no value changes
    operational(rig)
    rig.send(0x90, b"")
    assert rig.sniffer.wait_for(TPDO2, 1)                    # changed on entering OPERATIONAL
    rig.sniffer.clear()
    rig.send(0x80, b"")                                       # the old SYNC COB-ID is nobody's SYNC now
    for _ in range(3):
        rig.send(0x90, b"")
        time.sleep(0.01)
    assert rig.sniffer.of(TPDO2) == []
    rig.runner.call(rig.slave.write, 0x6064, 0, 4711)
    rig.send(0x90, b"")
    frames = rig.sniffer.wait_for(TPDO2, 1)
    assert struct.unpack_from("<i", frames[0][1], 2)[0] == 4711


def test_reset_communication_restores_the_default_mapping(rig):
    node = rig.node
    node.tpdo.read()
    node.tpdo[1].clear()
    node.tpdo[1].add_variable(0x6064)
    node.tpdo[1].save()
    assert node.sdo[0x1A00][0].raw == 1
    node.nmt.state = "RESET COMMUNICATION"
    assert rig.sniffer.wait_for(0x700 + NODE, 2, match=lambda d: d == b"\x00")
    assert node.sdo[0x1A00][0].raw == 2 and node.sdo[0x1A00][1].raw == 0x60410010
    operational(rig)
    frames = rig.sniffer.wait_for(TPDO1, 1)
    assert len(frames[-1][1]) == 3


def test_sync_timeout(rig):
    rig.node.sdo[0x1006].raw = 10000                        # 10 ms communication cycle
    operational(rig)
    time.sleep(0.05)
    assert rig.app.errors == []                              # monitoring starts with the first SYNC
    sync(rig, 3)
    assert rig.sniffer.wait_for(EMCY, match=lambda d: d[:2] == b"\x00\x81", timeout_s=1.0)
    assert wait_until(lambda: ("sync_timeout", 0) in rig.app.errors)
    sync(rig, 1)
    time.sleep(0.05)
    assert rig.slave.counters["sync_timeouts"] >= 2          # re-armed by the SYNC, lost again


def test_a_sync_of_pre_operational_answered_after_a_start_in_the_same_poll_sends_no_tpdo():
    """A busy host hands the node three SYNCs of PRE-OPERATIONAL and the NMT start after them in one poll: the
    SYNCs came while PDOs were off, so they get no TPDO (answered after the start, they used to get three: the
    conformance check 301-PDO-4 counted 8 TPDO1 for 5 SYNCs under load). A SYNC after the start gets its TPDO."""
    import can

    from virtualaxis.canopen_slave import CanopenSlave
    from virtualaxis.canopen_slave.testing import EDS_PATH

    channel = f"pdo-preop-{time.monotonic_ns()}"
    bus = can.Bus(interface="virtual", channel=channel)
    sniff = can.Bus(interface="virtual", channel=channel)
    try:
        slave = CanopenSlave(bus, NODE, EDS_PATH)
        slave.boot(0.0)
        slave.write(0x1800, 2, 1)  # TPDO1 synchronous, every SYNC
        tpdo1 = slave.read(0x1800, 1) & 0x7FF

        def frames(*msgs):
            for msg in msgs:
                slave.receive(msg)
            for counter in slave.poll(0.01):  # one poll: the frames as a late drive thread finds them
                slave.on_sync(counter, 0.01)
            out = []
            while (m := sniff.recv(0.05)) is not None:
                out.append(m.arbitration_id)
            return out

        sync = can.Message(arbitration_id=0x80, data=b"", is_extended_id=False)
        start = can.Message(arbitration_id=0x000, data=bytes((0x01, NODE)), is_extended_id=False)
        sent = frames(sync, sync, sync, start)
        assert sent.count(tpdo1) == 0, [hex(c) for c in sent]
        sent = frames(sync)
        assert sent.count(tpdo1) == 1, [hex(c) for c in sent]
    finally:
        sniff.shutdown()
        bus.shutdown()
