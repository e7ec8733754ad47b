"""NMT slave, heartbeat producer/consumer and node guarding through a real canopen master."""

from __future__ import annotations

import struct
import threading
import time

import canopen
import pytest

from virtualaxis.canopen_slave import NmtState
from virtualaxis.canopen_slave.testing import MasterRig, RecordingApp, wait_until

NODE = 9
HB = 0x700 + NODE
MASTER = 0x10


@pytest.fixture
def rig(tmp_path):
    app = RecordingApp()
    with MasterRig(NODE, app=app, store_path=tmp_path / "store.json") as r:
        app.slave = r.slave
        r.app = app
        yield r


def test_boot_up_and_pre_operational(rig):
    assert rig.sniffer.wait_for(HB)[0][1] == b"\x00"
    assert rig.slave.nmt_state == NmtState.PRE_OPERATIONAL
    assert rig.app.states == [NmtState.PRE_OPERATIONAL]


def test_heartbeat_producer_carries_the_state(rig):
    node = rig.node
    node.sdo[0x1017].raw = 20
    assert node.nmt.wait_for_heartbeat(timeout=1.0) == "PRE-OPERATIONAL"
    node.nmt.state = "OPERATIONAL"
    assert wait_until(lambda: rig.sniffer.of(HB)[-1][1] == b"\x05")
    node.nmt.state = "STOPPED"
    assert wait_until(lambda: rig.sniffer.of(HB)[-1][1] == b"\x04")
    node.nmt.state = "PRE-OPERATIONAL"
    assert wait_until(lambda: rig.sniffer.of(HB)[-1][1] == b"\x7f")
    rig.sniffer.clear()
    time.sleep(0.2)
    n = len(rig.sniffer.of(HB))
    assert 5 <= n <= 14                       # 20 ms period over 0.2 s (wide band: shared CI machine)
    node.sdo[0x1017].raw = 0
    time.sleep(0.05)
    rig.sniffer.clear()
    time.sleep(0.15)
    assert rig.sniffer.of(HB) == []


def test_stopped_answers_no_sdo_and_sends_no_pdo(rig):
    node = rig.node
    node.nmt.state = "OPERATIONAL"
    assert rig.sniffer.wait_for(0x180 + NODE, 1)        # TPDO1 sent on entering OPERATIONAL
    node.nmt.state = "STOPPED"
    assert wait_until(lambda: rig.slave.nmt_state == NmtState.STOPPED)
    rig.sniffer.clear()
    node.sdo.RESPONSE_TIMEOUT = 0.5  # no answer is expected: do not wait the rig's 2 s
    with pytest.raises(canopen.SdoCommunicationError):
        node.sdo.upload(0x1000, 0)
    node.sdo.RESPONSE_TIMEOUT = 2.0
    assert rig.slave.counters["sdo_ignored_stopped"] >= 1
    rig.network.sync.transmit()
    time.sleep(0.25)                                     # > TPDO1 event timer (100 ms)
    assert rig.sniffer.of(0x180 + NODE) == [] and rig.sniffer.of(0x280 + NODE) == []
    node.nmt.state = "OPERATIONAL"
    assert rig.sniffer.wait_for(0x180 + NODE, 1)
    assert node.sdo.upload(0x1000, 0) == struct.pack("<I", 0x00020192)


def test_reset_communication_restores_communication_defaults(rig):
    node = rig.node
    node.sdo[0x1017].raw = 50
    node.sdo[0x1800][5].raw = 500
    node.sdo[0x6081].raw = 4321
    node.nmt.state = "OPERATIONAL"
    rig.sniffer.clear()
    node.nmt.state = "RESET COMMUNICATION"
    assert rig.sniffer.wait_for(HB, match=lambda d: d == b"\x00")
    assert wait_until(lambda: rig.slave.nmt_state == NmtState.PRE_OPERATIONAL)
    assert node.sdo[0x1017].raw == 0
    assert node.sdo[0x1800][5].raw == rig.slave.od.entry(0x1800, 5).default
    assert node.sdo[0x6081].raw == 4321                  # application object kept
    assert rig.app.resets == [False]


def test_reset_node_restores_everything(rig):
    node = rig.node
    node.sdo[0x1017].raw = 50
    node.sdo[0x6081].raw = 4321
    rig.sniffer.clear()
    node.nmt.state = "RESET"
    assert rig.sniffer.wait_for(HB, match=lambda d: d == b"\x00")
    assert wait_until(lambda: rig.app.resets == [True])
    assert node.sdo[0x1017].raw == 0
    assert node.sdo[0x6081].raw == rig.slave.od.entry(0x6081).default
    assert rig.app.states[-1] == NmtState.PRE_OPERATIONAL


def test_nmt_for_other_nodes_and_malformed_nmt_are_ignored(rig):
    rig.nmt(0x01, NODE + 1)
    rig.nmt(0x81, NODE + 1)
    rig.send(0x000, b"\x01")                            # DLC 1
    rig.send(0x000, bytes((0x01, NODE, 0)))             # DLC 3
    rig.nmt(0x55)                                       # unknown command specifier
    assert wait_until(lambda: rig.slave.counters["nmt_invalid_command"] == 1)
    c = rig.slave.counters
    assert c["nmt_other_node_ignored"] == 2 and c["malformed_frames"] == 2
    assert rig.slave.nmt_state == NmtState.PRE_OPERATIONAL
    rig.nmt(0x01, 0)                                     # broadcast start
    assert wait_until(lambda: rig.slave.nmt_state == NmtState.OPERATIONAL)


class MasterHeartbeat:
    """The master's own heartbeat (node MASTER), stoppable."""

    def __init__(self, rig, period_s: float = 0.01):
        self.rig, self.period_s = rig, period_s
        self.stop_event = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        while not self.stop_event.is_set():
            self.rig.send(0x700 + MASTER, b"\x05")
            time.sleep(self.period_s)

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop()

    def stop(self):
        self.stop_event.set()
        self.thread.join()


def test_heartbeat_consumer_loss_reaction(rig):
    node = rig.node
    node.sdo[0x1016][1].raw = (MASTER << 16) | 100       # 100 ms
    node.nmt.state = "OPERATIONAL"
    emcy = 0x80 + NODE
    with MasterHeartbeat(rig):
        time.sleep(0.3)
        assert rig.app.errors == [] and rig.slave.nmt_state == NmtState.OPERATIONAL
    frames = rig.sniffer.wait_for(emcy, match=lambda d: d[:2] == b"\x30\x81", timeout_s=2.0)
    assert frames and frames[0][1][2] & 0x10                     # 0x1001 bit 4 communication error
    assert wait_until(lambda: rig.app.errors == [("heartbeat_lost", MASTER)])
    assert node.sdo[0x1001].raw & 0x11 == 0x11
    assert rig.slave.nmt_state == NmtState.PRE_OPERATIONAL        # 0x1029:1 = 0
    assert rig.slave.counters["heartbeat_timeouts"] == 1
    # re-armed by the next heartbeat; with 0x1029:1 = 1 the state does not change
    node.sdo[0x1029][1].raw = 1
    node.nmt.state = "OPERATIONAL"
    with MasterHeartbeat(rig):
        time.sleep(0.2)
    assert wait_until(lambda: len(rig.app.errors) == 2)
    assert rig.slave.nmt_state == NmtState.OPERATIONAL


def test_heartbeat_consumer_rejects_duplicate_nodes(rig):
    sdo = rig.node.sdo
    sdo[0x1016][1].raw = (MASTER << 16) | 100
    with pytest.raises(canopen.SdoAbortedError) as info:
        sdo[0x1016][2].raw = (MASTER << 16) | 200
    assert info.value.code == 0x06040043


def test_node_guarding_toggle_and_life_guarding(rig):
    node = rig.node
    node.sdo[0x100C].raw = 30                           # guard time ms
    node.sdo[0x100D].raw = 3                            # life time factor -> 90 ms
    rig.sniffer.clear()
    for _ in range(4):
        rig.send(HB, remote=True)
        time.sleep(0.02)
    replies = [d[0] for _t, d in rig.sniffer.wait_for(HB, 4)]
    assert [r & 0x7F for r in replies] == [0x7F] * 4
    assert [r >> 7 for r in replies] == [0, 1, 0, 1]
    node.nmt.state = "OPERATIONAL"
    rig.send(HB, remote=True)
    assert rig.sniffer.wait_for(HB, 5)[-1][1] == bytes((0x05,))     # toggle 0 again, state operational
    # no more guarding: life guarding event after 90 ms
    assert wait_until(lambda: ("life_guarding", NODE) in rig.app.errors, 1.0)
    assert rig.sniffer.wait_for(0x80 + NODE, match=lambda d: d[:2] == b"\x30\x81")
    assert rig.slave.counters["life_guarding_events"] >= 1


def test_node_guarding_via_canopen_master(rig):
    node = rig.node
    node.nmt.start_node_guarding(0.02)
    try:
        assert node.nmt.wait_for_heartbeat(timeout=1.0) == "PRE-OPERATIONAL"
    finally:
        node.nmt.stop_node_guarding()
    assert rig.slave.counters["node_guard_replies"] >= 1


def test_heartbeat_disables_node_guarding(rig):
    rig.node.sdo[0x1017].raw = 1000
    rig.sniffer.clear()
    rig.send(HB, remote=True)
    time.sleep(0.1)
    assert [d for _t, d in rig.sniffer.of(HB)] == []
