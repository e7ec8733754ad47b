"""EMCY producer (0x1001, 0x1003 history, 0x1014 COB-ID, 0x1015 inhibit, error reset) and store/restore
parameters (0x1010 "save" / 0x1011 "load") to a file, through a real canopen master."""

from __future__ import annotations

import json
import struct
import time

import canopen
import pytest

from virtualaxis.canopen_slave import CanopenSlave
from virtualaxis.canopen_slave import errors as ab
from virtualaxis.canopen_slave.testing import EDS_PATH, MasterRig, wait_until
from virtualaxis.config.errors import InputError

NODE = 13
EMCY = 0x80 + NODE


def test_emcy_frame_error_register_and_history():
    with MasterRig(NODE) as rig:
        node = rig.node
        received = []
        node.emcy.add_callback(received.append)
        rig.runner.call(rig.slave.emcy, 0x2310, 0x02, b"\x01\x02")
        rig.runner.call(rig.slave.emcy, 0x4210, 0x08)
        assert wait_until(lambda: len(received) == 2)
        assert received[0].code == 0x2310 and received[0].register == 0x03
        assert received[0].data == b"\x01\x02\x00\x00\x00"
        assert received[1].code == 0x4210 and received[1].register == 0x0B
        assert node.sdo[0x1001].raw == 0x0B
        assert node.sdo[0x603F].raw == 0x4210
        assert node.sdo[0x1003][0].raw == 2
        assert [node.sdo[0x1003][s].raw & 0xFFFF for s in (1, 2)] == [0x4210, 0x2310]   # newest first
        for value in (1, 8, 9, 255):  # any value but 0, also beyond the EDS HighLimit 8 (before: 9 -> 0x06090031)
            with pytest.raises(canopen.SdoAbortedError) as info:
                node.sdo[0x1003][0].raw = value
            assert info.value.code == ab.INVALID_VALUE, value
        node.sdo[0x1003][0].raw = 0                        # clears the history
        assert node.sdo[0x1003][0].raw == 0
        with pytest.raises(canopen.SdoAbortedError) as info:
            node.sdo.upload(0x1003, 1)
        assert info.value.code == ab.NO_DATA
        rig.runner.call(rig.slave.emcy_reset)
        assert wait_until(lambda: len(received) == 3)
        assert received[2].code == 0x0000 and received[2].register == 0
        assert node.sdo[0x1001].raw == 0 and node.sdo[0x603F].raw == 0
        assert rig.slave.counters["emcy_sent"] == 3


def test_emcy_inhibit_time_delays_and_cob_id_moves():
    with MasterRig(NODE) as rig:
        node = rig.node
        node.sdo[0x1015].raw = 300                          # 30 ms
        for code in (0x3210, 0x3220, 0x7320):
            rig.runner.call(rig.slave.emcy, code)
        frames = rig.sniffer.wait_for(EMCY, 3, timeout_s=1.0)
        assert [d[:2] for _t, d in frames] == [b"\x10\x32", b"\x20\x32", b"\x20\x73"]   # none dropped
        times = [t for t, _d in frames]
        assert min(b - a for a, b in zip(times, times[1:], strict=False)) > 0.025
        assert rig.slave.counters["emcy_inhibited"] == 2
        with pytest.raises(canopen.SdoAbortedError):
            node.sdo[0x1014].raw = 0x90                      # change while valid
        node.sdo[0x1014].raw = 0x80000000 | EMCY
        node.sdo[0x1014].raw = 0x90
        node.sdo[0x1015].raw = 0
        rig.runner.call(rig.slave.emcy, 0x8611)
        assert rig.sniffer.wait_for(0x90, match=lambda d: d[:2] == b"\x11\x86")


def test_store_and_restore_parameters(tmp_path):
    store = tmp_path / "params.json"
    with MasterRig(NODE, store_path=store) as rig:
        node = rig.node
        assert node.sdo[0x1010][1].raw == 1 and node.sdo[0x1011][1].raw == 1
        node.sdo[0x1017].raw = 250
        node.sdo[0x6065].raw = 777
        node.sdo[0x2000].raw = 4.5
        node.sdo[0x1010][1].raw = 0x65766173                # "save" all
        doc = json.loads(store.read_text())
        assert doc["values"]["1017sub0"] == 250 and doc["values"]["6065sub0"] == 777
        node.sdo[0x6065].raw = 1
        node.nmt.state = "RESET"                            # power-on values = stored values
        assert rig.sniffer.wait_for(0x700 + NODE, 2, match=lambda d: d == b"\x00")
        assert node.sdo[0x6065].raw == 777 and node.sdo[0x1017].raw == 250
        assert node.sdo[0x2000].raw == pytest.approx(4.5)
        node.sdo[0x1011][4].raw = 0x64616F6C                # "load" manufacturer defaults
        assert node.sdo[0x2000].raw == pytest.approx(4.5)   # effective after the next reset
        node.nmt.state = "RESET"
        assert rig.sniffer.wait_for(0x700 + NODE, 3, match=lambda d: d == b"\x00")
        assert node.sdo[0x2000].raw == pytest.approx(rig.slave.od.entry(0x2000).default)
        assert node.sdo[0x6065].raw == 777
    # a new slave on the same file (power cycle) starts from the stored values
    with MasterRig(NODE, store_path=store) as rig:
        assert rig.node.sdo[0x6065].raw == 777 and rig.node.sdo[0x1017].raw == 250
        rig.node.sdo[0x1011][1].raw = 0x64616F6C
        rig.node.nmt.state = "RESET"
        assert rig.sniffer.wait_for(0x700 + NODE, 2, match=lambda d: d == b"\x00")
        assert rig.node.sdo[0x6065].raw == rig.slave.od.entry(0x6065).default


def test_without_store_file_the_commands_are_refused():
    with MasterRig(NODE, store_path=None) as rig:
        assert rig.node.sdo[0x1010][1].raw == 0
        with pytest.raises(canopen.SdoAbortedError) as info:
            rig.node.sdo[0x1010][1].raw = 0x65766173
        assert info.value.code == ab.CANNOT_STORE


@pytest.mark.parametrize("content, message", [
    ("not json", "cannot read parameter store"),
    ('{"format": "other", "values": {}}', "not a parameter store file"),
    ('{"format": "virtualaxis canopen parameter store 1", "values": {"1000sub0": 1}}', "no writable object"),
    ('{"format": "virtualaxis canopen parameter store 1", "values": {"605Asub0": 9}}', "outside"),
    ('{"format": "virtualaxis canopen parameter store 1", "values": {"6065sub0": "x"}}', "expected a number"),
])
def test_bad_store_file_is_a_one_line_input_error(tmp_path, content, message):
    import can

    path = tmp_path / "bad.json"
    path.write_text(content)
    bus = can.Bus(interface="virtual", channel=f"bad-store-{tmp_path.name}")
    try:
        with pytest.raises(InputError) as info:
            CanopenSlave(bus, NODE, EDS_PATH, store_path=path)
        assert str(path) in str(info.value) and message in str(info.value)
        assert "\n" not in str(info.value)
    finally:
        bus.shutdown()


def test_bad_eds_and_node_id(tmp_path):
    import can

    bus = can.Bus(interface="virtual", channel=f"bad-eds-{tmp_path.name}")
    try:
        with pytest.raises(InputError, match="EDS file not found"):
            CanopenSlave(bus, NODE, tmp_path / "missing.eds")
        broken = tmp_path / "broken.eds"
        broken.write_text("[1000]\nParameterName=x\nDataType=zz\n")
        with pytest.raises(InputError, match=r"broken.eds: \[1000\] DataType = .zz.: expected an integer"):
            CanopenSlave(bus, NODE, broken)
        with pytest.raises(ValueError, match="node id"):
            CanopenSlave(bus, 128, EDS_PATH)
    finally:
        bus.shutdown()


def test_emcy_in_stopped_is_recorded_not_sent():
    with MasterRig(NODE) as rig:
        rig.node.nmt.state = "STOPPED"
        assert wait_until(lambda: int(rig.slave.nmt_state) == 4)
        rig.runner.call(rig.slave.emcy, 0x2310)
        time.sleep(0.05)
        assert rig.sniffer.of(EMCY) == []
        assert rig.slave.read(0x1003, 0) == 1 and rig.slave.read(0x1001) & 1
        assert struct.unpack("<I", struct.pack("<I", rig.slave.read(0x1003, 1)))[0] & 0xFFFF == 0x2310
