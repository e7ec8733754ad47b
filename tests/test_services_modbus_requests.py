"""Modbus TCP requests as a raw socket sends them: long pipelines on one connection, every function code
0x00..0xFF, PDUs too short or too long for their function, frames of another protocol. Each request gets
exactly one answer, in order, with the exception the Modbus application protocol names; the server logs no
traceback."""

from __future__ import annotations

import socket
import struct

import pytest
from test_services_modbus import Server, make_drive

from virtualaxis.services.modbus import SUPPORTED_FUNCTIONS
from virtualaxis.services.modbus_map import (
    REASON_BAD_COUNT,
    REASON_BAD_LENGTH,
    REASON_UNKNOWN_REGISTER,
    REASON_UNSUPPORTED_FUNCTION,
)

pytestmark = pytest.mark.exclusive  # timing-sensitive: background jobs stopped meanwhile


@pytest.fixture(scope="module")
def server():
    s = Server({1: make_drive()})
    yield s
    s.close()


def _adu(tid: int, pdu: bytes, unit: int = 1, pid: int = 0) -> bytes:
    return struct.pack(">HHHB", tid, pid, len(pdu) + 1, unit) + pdu


def _answers(sock: socket.socket, n: int) -> list[tuple[int, bytes]]:
    """``n`` answers (transaction id, PDU) read from ``sock``."""
    data, out = b"", []
    while len(out) < n:
        chunk = sock.recv(65536)
        assert chunk, f"connection closed after {len(out)} of {n} answers"
        data += chunk
        while len(data) >= 7 and len(data) >= 6 + struct.unpack(">H", data[4:6])[0]:
            size = 6 + struct.unpack(">H", data[4:6])[0]
            out.append((struct.unpack(">H", data[:2])[0], data[7:size]))
            data = data[size:]
    return out


def _exchange(server: Server, frames: list[bytes], n_answers: int, *, in_pieces: int = 0) -> list[tuple[int, bytes]]:
    """Send ``frames`` in one ``sendall`` (or cut into pieces of ``in_pieces`` bytes) and read the answers;
    then check that nothing more comes."""
    stream = b"".join(frames)
    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as s:
        if in_pieces:
            for i in range(0, len(stream), in_pieces):
                s.sendall(stream[i : i + in_pieces])
        else:
            s.sendall(stream)
        answers = _answers(s, n_answers)
        s.settimeout(0.3)
        try:
            extra = s.recv(4096)
        except TimeoutError:
            extra = b""
    assert extra == b"", f"more answers than requests: {extra!r}"
    return answers


@pytest.mark.parametrize("n", [1, 22, 23, 24, 100, 2000])
def test_a_pipeline_of_n_requests_in_one_send_gets_n_answers_in_order(server, n):
    server.svc.sync()
    kinds = [struct.pack(">BHH", 3, 40110 - 40001, 2), struct.pack(">BHH", 4, 40361 - 40001, 1),
             struct.pack(">BHH", 3, 0, 1), bytes([0x2B, 0x0E, 0x01, 0x00])]  # read, read, hole (02), FC43 (01)
    frames = [_adu(i + 1, kinds[i % 4]) for i in range(n)]
    answers = _exchange(server, frames, n)
    assert [tid for tid, _ in answers] == list(range(1, n + 1))
    for i, (_tid, pdu) in enumerate(answers):
        assert pdu[:2] == [bytes([3, 4]), bytes([4, 2]), bytes([0x83, 2]), bytes([0xAB, 1])][i % 4], (i, pdu)


def test_a_pipeline_cut_at_every_odd_boundary_is_answered_whole(server):
    frames = [_adu(i + 1, struct.pack(">BHH", 3, 40110 - 40001, 1)) for i in range(300)]
    answers = _exchange(server, frames, 300, in_pieces=7)
    assert [tid for tid, _ in answers] == list(range(1, 301))
    assert all(pdu[:2] == bytes([3, 2]) for _, pdu in answers)


def test_every_function_code_gets_one_answer_unsupported_ones_exception_01(server, capfd):
    """0x00..0xFF, each as a well-formed request of 4 data bytes, all in one pipeline: the map's functions
    answer normally or with their own exception, every other code (0x80..0xFF too) with exception 01, whose
    function byte is the code with bit 7 set; no traceback is logged."""
    body = struct.pack(">HH", 40110 - 40001, 1)
    frames = [_adu(fc + 1, bytes([fc]) + body) for fc in range(256)]
    answers = _exchange(server, frames, 256)
    assert [tid for tid, _ in answers] == [fc + 1 for fc in range(256)]
    for fc, (_tid, pdu) in enumerate(answers):
        if fc in SUPPORTED_FUNCTIONS:
            assert pdu[0] in (fc, fc | 0x80) and pdu[1:] != b"\x01", (fc, pdu)
        else:
            assert pdu == bytes([fc | 0x80, 0x01]), (fc, pdu)
    assert server.last_error()[0] in (REASON_UNSUPPORTED_FUNCTION, REASON_BAD_LENGTH)
    err = capfd.readouterr().err
    assert "Traceback" not in err and "Datastore unable" not in err


@pytest.mark.parametrize("fc,data", [
    (3, b""), (3, b"\x00"), (3, b"\x00\x6d\x00"), (3, b"\x00\x6d\x00\x01\x00"),
    (4, b""), (4, b"\x00\x6d\x00"),
    (6, b""), (6, b"\x00\x63\x00"),
    (16, b""), (16, b"\x00\x63\x00\x01"),
    (23, b""), (23, b"\x00\x6d\x00\x01\x00\x63\x00\x01"),
])
def test_a_pdu_too_short_or_too_long_for_its_function_is_exception_03(server, fc, data):
    answers = _exchange(server, [_adu(7, bytes([fc]) + data), _adu(8, struct.pack(">BHH", 3, 40110 - 40001, 1))], 2)
    assert answers[0] == (7, bytes([fc | 0x80, 0x03]))
    assert answers[1][0] == 8 and answers[1][1][:2] == bytes([3, 2])  # the next request is served
    reason, _address, _abort = server.last_error()
    assert reason == REASON_BAD_LENGTH


W = 40100 - 40001  # a writable register (PDU address)


BYTE_COUNT_CASES = [
    ("FC16 byte count 4 for 1 register", struct.pack(">BHHB", 16, W, 1, 4) + bytes(4), REASON_BAD_LENGTH),
    ("FC16 byte count 2 for 2 registers", struct.pack(">BHHB", 16, W, 2, 2) + bytes(2), REASON_BAD_LENGTH),
    ("FC16 byte count 2, 4 bytes sent", struct.pack(">BHHB", 16, W, 1, 2) + bytes(4), REASON_BAD_LENGTH),
    ("FC16 byte count 4, 2 bytes sent", struct.pack(">BHHB", 16, W, 2, 4) + bytes(2), REASON_BAD_LENGTH),
    ("FC16 124 registers", struct.pack(">BHHB", 16, W, 124, 248) + bytes(248), REASON_BAD_COUNT),
    ("FC23 write byte count 2 for 2", struct.pack(">BHHHHB", 23, W, 1, W, 2, 2) + bytes(2), REASON_BAD_LENGTH),
    ("FC23 write byte count 4 for 1", struct.pack(">BHHHHB", 23, W, 1, W, 1, 4) + bytes(4), REASON_BAD_LENGTH),
    ("FC23 write byte count 2, 4 bytes", struct.pack(">BHHHHB", 23, W, 1, W, 1, 2) + bytes(4), REASON_BAD_LENGTH),
    ("FC23 write byte count 4, 2 bytes", struct.pack(">BHHHHB", 23, W, 1, W, 2, 4) + bytes(2), REASON_BAD_LENGTH),
]


@pytest.mark.parametrize("name,pdu,reason", BYTE_COUNT_CASES, ids=[c[0] for c in BYTE_COUNT_CASES])
def test_a_byte_count_that_does_not_fit_is_exception_03_with_its_reason(server, name, pdu, reason):
    """The byte count of FC16 / FC23 must be 2 x the register count and the number of data bytes sent; a request
    where it is not is refused with 03 and its reason in the last-error registers (the registers first hold
    another error, so a reason left from before cannot pass), nothing written."""
    before = server.last_error()
    answers = _exchange(server, [_adu(1, struct.pack(">BHH", 3, 40002 - 40001, 1))], 1)  # reason 7 first
    assert answers[0] == (1, bytes([0x83, 0x02]))
    assert server.last_error()[0] == REASON_UNKNOWN_REGISTER, before
    answers = _exchange(server, [_adu(2, pdu)], 1)
    assert answers[0] == (2, bytes([pdu[0] | 0x80, 0x03])), name
    got, address, abort = server.last_error()
    assert (got, address, abort) == (reason, W, 0), name


def test_frames_of_another_protocol_are_skipped_and_the_stream_stays_in_step(server):
    read = struct.pack(">BHH", 3, 40110 - 40001, 1)
    answers = _exchange(server, [_adu(1, read), _adu(2, read, pid=7), _adu(3, read)], 2)
    assert [tid for tid, _ in answers] == [1, 3]



@pytest.mark.parametrize("in_pieces", [0, 1], ids=["one-send", "byte-by-byte"])
def test_frames_without_a_function_code_are_skipped_and_the_stream_stays_in_step(server, in_pieces):
    """An MBAP length of 0 (not even the unit id) or 1 (the unit id only) frames no request, but the frame still
    ends where its length says: the requests after it are answered (a docs-only tester's valid request after a
    length-0 header went unanswered, and after a length-1 one none in the same segment)."""
    read = struct.pack(">BHH", 3, 40110 - 40001, 1)
    no_unit = struct.pack(">HHH", 2, 0, 0)
    unit_only = struct.pack(">HHHB", 4, 0, 1, 1)
    answers = _exchange(server, [_adu(1, read), no_unit, _adu(3, read), unit_only, _adu(5, read), _adu(6, read)],
                        4, in_pieces=in_pieces)
    assert [tid for tid, _ in answers] == [1, 3, 5, 6]
    assert all(pdu[:2] == bytes([3, 2]) for _, pdu in answers)

@pytest.fixture
def fresh():
    s = Server({1: make_drive()})
    yield s
    s.close()


def test_one_read_is_one_drive_instant(fresh):
    """FC03 of the monitoring block 40340-40383 while the drive runs a CSP sine (the runtime's thread steps it
    meanwhile): 40345 actual current (0.01 A) and 40355 0x6078 (per mille of the rated current) of every read
    agree to their resolution."""
    import math
    import threading

    from test_drive_rig import seed_config
    from test_services_modbus import csp_enable

    drive = fresh.links[1].drive
    csp_enable(drive)
    rated_a = seed_config().motor.rated_current_a
    stop = threading.Event()

    def run() -> None:
        k = 0
        while not stop.is_set():
            k += 1
            drive.write_object(0x607A, 0, int(round(3000 * math.sin(k * 0.05))))
            drive.step(1)

    stepper = threading.Thread(target=run, daemon=True)
    stepper.start()
    try:
        worst = 0.0
        for _ in range(300):
            r = fresh.client.read_holding_registers(40340 - 40001, count=44, device_id=1)
            assert not r.isError()
            w = [v - 0x10000 if v & 0x8000 else v for v in r.registers]
            current_a, permille = w[5] / 100.0, w[15]
            worst = max(worst, abs(current_a - permille * rated_a / 1000.0))
    finally:
        stop.set()
        stepper.join()
    assert abs(drive.state.current_a) > 0.1 or worst > 0  # (the sine moves the axis: the current changes)
    assert worst <= 0.005 + rated_a / 2000.0 + 1e-9, worst


def test_stw1_without_bit_10_leaves_the_axis_to_its_master(fresh):
    """STW1 bit 10 = 0 ("no control by PLC"): the write is answered and ignored; with bit 10 it is obeyed."""
    drive = fresh.links[1].drive
    csp = fresh.client
    from test_services_modbus import csp_enable

    csp_enable(drive)  # (what a CANopen master did)
    for word in (0x0000, 0x0006, 0x0002, 0x0080, 0x007E, 0x03FF, 0xFBFF):
        assert not csp.write_register(40100 - 40001, word, device_id=1).isError()
        drive.step(1)
        assert drive.state.cia402_state == "OPERATION ENABLED", hex(word)
    assert not csp.write_registers(40100 - 40001, [0x0000], device_id=1).isError()  # FC16 alike
    drive.step(1)
    assert drive.state.cia402_state == "OPERATION ENABLED"
    assert not csp.write_register(40100 - 40001, 0x0400, device_id=1).isError()  # bit 10 alone: OFF1
    drive.step(1)
    assert drive.state.cia402_state == "SWITCH ON DISABLED"
