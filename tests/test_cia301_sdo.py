"""SDO server through a real canopen master and raw client frames: every abort code, expedited,
segmented, block download and block upload (with CRC, protocol switch and sequence recovery)."""

from __future__ import annotations

import queue
import struct
import time

import canopen
import pytest

from virtualaxis.canopen_slave import errors as ab
from virtualaxis.canopen_slave.counters import abort_key
from virtualaxis.canopen_slave.errors import ABORT_CODES
from virtualaxis.canopen_slave.sdo_server import crc16
from virtualaxis.canopen_slave.testing import MasterRig, RecordingApp

NODE = 7
RX, TX = 0x600 + NODE, 0x580 + NODE


@pytest.fixture
def rig(tmp_path):
    app = RecordingApp()
    with MasterRig(NODE, app=app, store_path=tmp_path / "store.json") as r:
        app.slave = r.slave
        r.app = app
        yield r


def raw(rig, frame: bytes, expect: int = 1, timeout_s: float = 1.0) -> list[bytes]:
    """Send one raw SDO request (8 bytes) and return the next `expect` server frames."""
    time.sleep(0.01)              # the sniffer's notifier thread may still be delivering earlier answers
    before = len(rig.sniffer.of(TX))
    rig.send(RX, frame.ljust(8, b"\x00"))
    got = rig.sniffer.wait_for(TX, before + expect, timeout_s)
    # The master's own SDO client hears these answers too, on its notifier thread, possibly after the sniffer:
    # let them arrive and drop them, so a later client request cannot take a stale answer for its own.
    time.sleep(0.05)
    rig.node.sdo.responses = queue.Queue()
    return [d for _t, d in got[before:]]


def abort_code(frame: bytes) -> int:
    assert frame[0] == 0x80, frame.hex()
    return struct.unpack_from("<I", frame, 4)[0]


def sdo_abort(fn, *args) -> int:
    with pytest.raises(canopen.SdoAbortedError) as info:
        fn(*args)
    return info.value.code


def mux(index: int, sub: int) -> bytes:
    return struct.pack("<HB", index, sub)


# ---------------------------------------------------------------- object access aborts
def test_object_and_subindex_do_not_exist(rig):
    sdo = rig.node.sdo
    assert sdo_abort(sdo.upload, 0x5FFF, 0) == ab.NO_OBJECT
    assert sdo_abort(sdo.download, 0x3000, 0, b"\x01") == ab.NO_OBJECT
    assert sdo_abort(sdo.upload, 0x1018, 5) == ab.NO_SUBINDEX
    assert sdo_abort(sdo.upload, 0x607D, 3) == ab.NO_SUBINDEX        # past the ARRAY's sub0 = 2
    assert sdo_abort(sdo.upload, 0x6092, 0x10) == ab.NO_SUBINDEX
    assert sdo_abort(sdo.upload, 0x6040, 1) == ab.NO_SUBINDEX        # VAR has only sub 0
    assert sdo_abort(sdo.upload, 0x1003, 1) == ab.NO_DATA            # empty error history


def test_access_types(rig):
    sdo = rig.node.sdo
    assert sdo_abort(sdo.download, 0x1000, 0, struct.pack("<I", 0x20192)) == ab.WRITE_READ_ONLY
    assert sdo_abort(sdo.download, 0x6041, 0, b"\x00\x00") == ab.WRITE_READ_ONLY
    assert sdo_abort(sdo.download, 0x1018, 1, b"\x00\x00\x00\x00") == ab.WRITE_READ_ONLY
    assert sdo_abort(sdo.upload, 0x2102, 0) == ab.READ_WRITE_ONLY


def test_wrong_lengths(rig):
    sdo = rig.node.sdo
    assert sdo_abort(sdo.download, 0x6040, 0, b"\x01\x02\x03\x04") == ab.LENGTH_TOO_HIGH    # U16
    assert sdo_abort(sdo.download, 0x6081, 0, b"\x01") == ab.LENGTH_TOO_LOW                 # U32
    # segmented download announcing 4 bytes that delivers 3: data type length does not match
    assert raw(rig, bytes((0x21,)) + mux(0x6081, 0) + struct.pack("<I", 4))[0][0] == 0x60
    assert abort_code(raw(rig, bytes((0x00 | (4 << 1) | 1, 1, 2, 3)))[0]) == ab.LENGTH_MISMATCH
    # segmented download announcing more than the object holds
    too_long = bytes((0x21,)) + mux(0x6081, 0) + struct.pack("<I", 9)
    assert abort_code(raw(rig, too_long)[0]) == ab.LENGTH_TOO_HIGH
    assert rig.slave.read(0x6081) == rig.slave.od.entry(0x6081).default


def test_value_range_and_invalid_values(rig):
    sdo = rig.node.sdo
    assert sdo_abort(sdo.download, 0x605A, 0, struct.pack("<h", 9)) == ab.VALUE_TOO_HIGH
    assert sdo_abort(sdo.download, 0x605A, 0, struct.pack("<h", -1)) == ab.VALUE_TOO_LOW
    assert sdo_abort(sdo.download, 0x2000, 0, struct.pack("<f", 2001.0)) == ab.VALUE_TOO_HIGH
    assert sdo_abort(sdo.download, 0x2000, 0, struct.pack("<f", float("nan"))) == ab.INVALID_VALUE
    assert sdo_abort(sdo.download, 0x1019, 0, b"\x01") == ab.INVALID_VALUE
    assert sdo_abort(sdo.download, 0x1003, 0, b"\x02") == ab.INVALID_VALUE
    assert sdo_abort(sdo.download, 0x1400, 2, b"\xF5") == ab.INVALID_VALUE       # reserved type 245
    assert rig.slave.read(0x605A) == 2


def test_mode_not_in_6502_is_refused_by_the_application(rig):
    sdo = rig.node.sdo
    sdo.download(0x6060, 0, struct.pack("<b", 8))
    assert sdo.upload(0x6061, 0) == b"\x08"
    assert sdo_abort(sdo.download, 0x6060, 0, struct.pack("<b", 2)) == ab.INVALID_VALUE   # VL not supported
    assert sdo.upload(0x6061, 0) == b"\x08"
    assert rig.slave.read(0x6060) == 8


def test_application_refusals_and_bugs(rig):
    sdo = rig.node.sdo
    rig.app.refuse[(0x6081, 0)] = ab.LOCAL_CONTROL
    assert sdo_abort(sdo.download, 0x6081, 0, struct.pack("<I", 5)) == ab.LOCAL_CONTROL
    rig.app.refuse[(0x6083, 0)] = ab.DEVICE_STATE
    assert sdo_abort(sdo.download, 0x6083, 0, struct.pack("<I", 5)) == ab.DEVICE_STATE
    rig.app.explode.add((0x6084, 0))
    assert sdo_abort(sdo.download, 0x6084, 0, struct.pack("<I", 5)) == ab.GENERAL_ERROR
    assert rig.slave.counters["internal_errors"] == 1
    assert rig.slave.read(0x6081) == rig.slave.od.entry(0x6081).default
    sdo.download(0x6085, 0, struct.pack("<I", 123))           # still serving
    assert (0x6085, 0, 123) in rig.app.writes
    sdo.upload(0x6064, 0)
    assert (0x6064, 0) in rig.app.reads
    rig.app.refuse.clear()
    rig.app.explode.clear()


def test_pdo_mapping_while_valid_is_refused(rig):
    sdo = rig.node.sdo
    assert sdo_abort(sdo.download, 0x1A00, 0, b"\x00") == ab.DEVICE_STATE
    assert sdo_abort(sdo.download, 0x1600, 1, struct.pack("<I", 0x60400010)) == ab.DEVICE_STATE


def test_store_signature_and_hardware_error(rig, tmp_path):
    sdo = rig.node.sdo
    assert sdo_abort(sdo.download, 0x1010, 1, struct.pack("<I", 0x12345678)) == ab.CANNOT_STORE
    assert sdo_abort(sdo.download, 0x1011, 1, b"save") == ab.CANNOT_STORE
    rig.slave.store.path = tmp_path / "missing-dir" / "store.json"
    assert sdo_abort(sdo.download, 0x1010, 1, b"save") == ab.HARDWARE_ERROR


# ---------------------------------------------------------------- protocol aborts (raw frames)
def test_unknown_command_specifiers(rig):
    assert abort_code(raw(rig, bytes((0xE0,)) + mux(0x1000, 0))[0]) == ab.UNKNOWN_COMMAND
    assert abort_code(raw(rig, bytes((0x00, 1, 2, 3)))[0]) == ab.UNKNOWN_COMMAND        # segment, no transfer
    assert abort_code(raw(rig, bytes((0x60,)))[0]) == ab.UNKNOWN_COMMAND                # upload segment
    assert abort_code(raw(rig, bytes((0xA3,)))[0]) == ab.UNKNOWN_COMMAND                # block start, no init
    assert rig.slave.counters["sdo_unknown_command"] == 4


def test_toggle_bit_error(rig):
    first = raw(rig, bytes((0x40,)) + mux(0x1008, 0))[0]
    assert first[0] == 0x41 and struct.unpack_from("<I", first, 4)[0] == len("virtualaxis servo drive")
    assert raw(rig, bytes((0x60,)))[0][0] & 0x10 == 0
    assert abort_code(raw(rig, bytes((0x60,)))[0]) == ab.TOGGLE_BIT      # toggle should be 1 now
    assert rig.slave.counters["sdo_toggle_errors"] == 1


def test_sdo_timeout_aborts_a_stalled_transfer(rig):
    before = len(rig.sniffer.of(TX))
    assert raw(rig, bytes((0x21,)) + mux(0x6081, 0) + struct.pack("<I", 4))[0][0] == 0x60
    frames = rig.sniffer.wait_for(TX, before + 2, timeout_s=3.0)
    assert abort_code(frames[-1][1]) == ab.SDO_TIMEOUT
    time.sleep(0.05)              # let the master's notifier deliver it too (canopen drops stale answers)


def test_block_upload_invalid_block_size(rig):
    assert abort_code(raw(rig, bytes((0xA4,)) + mux(0x1008, 0) + bytes((0, 0)))[0]) == ab.INVALID_BLOCK_SIZE
    assert abort_code(raw(rig, bytes((0xA4,)) + mux(0x1008, 0) + bytes((128, 0)))[0]) == ab.INVALID_BLOCK_SIZE


def test_block_download_sequence_and_crc(rig):
    value = struct.pack("<I", 4242)
    init = bytes((0xC6,)) + mux(0x6081, 0) + struct.pack("<I", 4)
    # invalid sequence number 0
    assert raw(rig, init)[0][0] == 0xA4
    assert abort_code(raw(rig, bytes((0x00,)) + value)[0]) == ab.INVALID_SEQUENCE
    # CRC error
    assert raw(rig, init)[0][0] == 0xA4
    assert raw(rig, bytes((0x81,)) + value)[0][:2] == b"\xA2\x01"
    bad = (crc16(value) ^ 0xFFFF)
    assert abort_code(raw(rig, bytes((0xC1 | (3 << 2),)) + struct.pack("<H", bad))[0]) == ab.CRC_ERROR
    assert rig.slave.read(0x6081) == rig.slave.od.entry(0x6081).default
    # a lost segment: seq 2 arrives first -> ack 0, the client repeats from seq 1, then a good CRC
    ack = raw(rig, init)[0]
    assert ack[0] == 0xA4 and ack[4] == 127
    assert raw(rig, bytes((0x82,)) + value)[0][:2] == b"\xA2\x00"
    assert raw(rig, bytes((0x81,)) + value)[0][:2] == b"\xA2\x01"
    assert raw(rig, bytes((0xC1 | (3 << 2),)) + struct.pack("<H", crc16(value)))[0][0] == 0xA1
    assert rig.slave.read(0x6081) == 4242


def test_every_abort_code_is_counted_in_0x2101_and_counters(rig, tmp_path):
    test_object_and_subindex_do_not_exist(rig)
    test_access_types(rig)
    test_wrong_lengths(rig)
    test_value_range_and_invalid_values(rig)
    test_application_refusals_and_bugs(rig)
    test_store_signature_and_hardware_error(rig, tmp_path)
    test_unknown_command_specifiers(rig)
    test_toggle_bit_error(rig)
    test_block_upload_invalid_block_size(rig)
    test_block_download_sequence_and_crc(rig)
    test_sdo_timeout_aborts_a_stalled_transfer(rig)
    sdo = rig.node.sdo
    sdo.download(0x1803, 1, struct.pack("<I", 0xC0000480 + NODE))
    sdo.download(0x1A03, 0, b"\x00")
    assert sdo_abort(sdo.download, 0x1A03, 1, struct.pack("<I", 0x10000020)) == ab.NOT_MAPPABLE
    for sub, obj in ((1, 0x60640020), (2, 0x606C0020), (3, 0x60F40020)):
        sdo.download(0x1A03, sub, struct.pack("<I", obj))
    assert sdo_abort(sdo.download, 0x1A03, 0, b"\x03") == ab.MAPPING_TOO_LONG
    assert sdo_abort(sdo.download, 0x1A03, 1, struct.pack("<I", 0x60640010)) == ab.PARAMETER_INCOMPATIBLE
    never_sent = {ab.UNSUPPORTED_ACCESS}   # no object of this EDS has an access the server cannot serve
    counted = rig.slave.counters
    for sub, code in enumerate(ABORT_CODES, start=1):
        served = struct.unpack("<I", sdo.upload(0x2101, sub))[0]
        assert served == counted[abort_key(code)]
        if code not in never_sent:
            assert served >= 1, f"abort 0x{code:08X} never produced"
    total = struct.unpack("<I", sdo.upload(0x2100, 3))[0]
    assert total == sum(counted[abort_key(c)] for c in ABORT_CODES)
    sdo.download(0x2102, 0, b"\x01")                       # reset counters (write-only object)
    assert struct.unpack("<I", sdo.upload(0x2101, ABORT_CODES.index(ab.NO_OBJECT) + 1))[0] == 0


# ---------------------------------------------------------------- transfers
def test_expedited_segmented_and_block_transfers(rig):
    sdo = rig.node.sdo
    name = "virtualaxis servo drive"
    assert sdo[0x1008].raw == name                                  # segmented upload
    with sdo[0x1008].open("rb", block_transfer=True) as f:          # block upload with CRC
        assert f.read().decode() == name
    with sdo[0x1018][4].open("rb", block_transfer=True) as f:       # block upload of 4 bytes
        assert struct.unpack("<I", f.read())[0] == 1
    sdo.download(0x6081, 0, struct.pack("<I", 777), force_segment=True)   # segmented download
    assert rig.slave.read(0x6081) == 777
    with sdo[0x6083].open("wb", block_transfer=True, size=4) as f:        # block download with CRC
        f.write(struct.pack("<I", 888))
    assert rig.slave.read(0x6083) == 888
    sdo[0x6084].raw = 999                                                  # expedited
    assert sdo[0x6084].raw == 999
    # block upload with the protocol switch threshold: 4 bytes <= pst 8 -> expedited answer
    answer = raw(rig, bytes((0xA4,)) + mux(0x1000, 0) + bytes((127, 8)))[0]
    assert answer[0] == 0x43 and struct.unpack_from("<I", answer, 4)[0] == 0x00020192
    # expedited without size indication
    assert raw(rig, bytes((0x22,)) + mux(0x6040, 0) + b"\x06\x00\x00\x00")[0][0] == 0x60
    assert rig.slave.read(0x6040) == 6


def test_client_abort_ends_a_transfer(rig):
    assert raw(rig, bytes((0x40,)) + mux(0x1008, 0))[0][0] == 0x41
    rig.send(RX, bytes((0x80,)) + mux(0x1008, 0) + struct.pack("<I", ab.GENERAL_ERROR))
    time.sleep(0.05)
    assert rig.slave.counters["sdo_aborts_received"] == 1
    assert abort_code(raw(rig, bytes((0x60,)))[0]) == ab.UNKNOWN_COMMAND


def test_block_upload_in_small_sub_blocks_with_a_repeat(rig):
    """Block size 2: 23 bytes = 4 segments = 2 sub-blocks; the client acknowledges only 1 segment of the
    first sub-block once, so the server must resend from segment 2."""
    name = b"virtualaxis servo drive"
    init = raw(rig, bytes((0xA4,)) + mux(0x1008, 0) + bytes((2, 0)))[0]
    assert init[0] == 0xC6 and struct.unpack_from("<I", init, 4)[0] == len(name)
    seg = raw(rig, bytes((0xA3,)), expect=2)
    assert [s[0] for s in seg] == [1, 2]
    data = bytearray(seg[0][1:])                            # keep segment 1 only
    seg = raw(rig, bytes((0xA2, 1, 2)), expect=2)           # ack seq 1 -> resend from byte 7
    assert [s[0] for s in seg] == [1, 2]
    data += seg[0][1:] + seg[1][1:]
    seg = raw(rig, bytes((0xA2, 2, 2)), expect=1)           # last sub-block: one segment (2 bytes)
    assert seg[0][0] == 0x81
    data += seg[0][1:]
    end = raw(rig, bytes((0xA2, 1, 2)))[0]
    unused = (end[0] >> 2) & 7
    assert end[0] & 0xE3 == 0xC1 and unused == 5
    payload = bytes(data[:len(data) - unused])
    assert payload == name
    assert struct.unpack_from("<H", end, 1)[0] == crc16(name)
    requests = rig.slave.counters["sdo_requests"]
    rig.send(RX, bytes((0xA1,)).ljust(8, b"\x00"))          # client end: no answer, transfer done
    deadline = time.monotonic() + 1.0
    while rig.slave.counters["sdo_requests"] == requests and time.monotonic() < deadline:
        time.sleep(0.002)
    assert rig.slave.sdo.state == 0
    assert rig.slave.counters["sdo_aborts_sent"] == 0
