"""Every frame from the bus is counted and then applied or dropped: raw udp_multicast datagrams (hop limit 0)
of every malformed kind sent to `virtualaxis serve` in another process, which keeps serving, counts them
(--json runtime statistics, each axis' 0x2100:1 malformed frames) and never reports a bus load above 100 %."""

from __future__ import annotations

import json
import socket
import time

import can
import msgpack
import pytest
from served_drive import served

from virtualaxis.runtime.frames import MalformedFrame, decode_datagram, frame_problem

BASE = {"timestamp": 0.0, "arbitration_id": 0x123, "is_extended_id": False, "is_remote_frame": False,
        "is_error_frame": False, "channel": "test", "dlc": 2, "data": b"\x01\x02", "is_fd": False,
        "bitrate_switch": False, "error_state_indicator": False}


def _packed(**change) -> bytes:
    fields = dict(BASE)
    for key, value in change.items():
        if value is _DROP:
            fields.pop(key)
        else:
            fields[key] = value
    return msgpack.packb(fields, use_bin_type=True)


_DROP = object()

#: datagrams no CAN controller could have received (name -> datagram)
MALFORMED = {
    "id 3.5": _packed(arbitration_id=3.5),
    "id 0.0 (a float, not the NMT COB-ID)": _packed(arbitration_id=0.0),
    "id as text": _packed(arbitration_id="0x601"),
    "id none": _packed(arbitration_id=None),
    "id true": _packed(arbitration_id=True),
    "id negative": _packed(arbitration_id=-1),
    "11-bit id 0x800": _packed(arbitration_id=0x800),
    "29-bit id 2^29": _packed(arbitration_id=1 << 29, is_extended_id=True),
    "id 2^63": _packed(arbitration_id=1 << 63),
    "dlc 9": _packed(dlc=9, data=b"\x00" * 9),
    "dlc negative": _packed(dlc=-1),
    "dlc 2.0": _packed(dlc=2.0),
    "dlc as text": _packed(dlc="2"),
    "dlc 8, 2 data bytes": _packed(dlc=8),
    "dlc 0, 2 data bytes": _packed(dlc=0),
    "data as text": _packed(data="ab"),
    "data as a small integer": _packed(data=2),
    "data as a huge integer": _packed(data=10**15),
    "data as a list": _packed(data=[1, 2]),
    "data as a map": _packed(data={"a": 1}),
    "extended flag as text": _packed(is_extended_id="yes"),
    "extended flag as 1": _packed(is_extended_id=1),
    "remote flag as 1": _packed(is_remote_frame=1),
    "remote and error frame": _packed(is_remote_frame=True, is_error_frame=True, dlc=0, data=b""),
    "CAN FD frame": _packed(is_fd=True),
    "bit rate switch without FD": _packed(bitrate_switch=True),
    "unknown field": _packed(flavour="salty"),
    "integer map key": msgpack.packb({1: 2}),
    "not a map (integer)": msgpack.packb(5),
    "not a map (list)": msgpack.packb([0x601, b"\x40\x00\x10\x00\x00\x00\x00\x00"]),
    "not msgpack": b"\xc1 not msgpack",
    "empty datagram": b"",
    "truncated map": _packed()[:20],
}
#: well-formed frames no axis takes: dropped as unrouted / error frames
ERROR_FRAME = _packed(is_error_frame=True, arbitration_id=0x80, is_extended_id=True, dlc=8, data=bytes(8))
UNROUTED = [
    _packed(arbitration_id=0x601, is_extended_id=True, dlc=8, data=bytes(8)),  # 29-bit frame with an SDO's id
    _packed(arbitration_id=0x123, is_remote_frame=True, dlc=2, data=b""),      # remote frame nobody answers
    _packed(arbitration_id=0x7E5, dlc=1, data=b"\x00"),                        # (LSS): no axis listens
]


def _sender(group: str, port: int) -> socket.socket:
    raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    raw.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)  # hop limit 0: never leaves the host
    raw.connect((group, port))
    return raw


def _sdo_read(bus: can.BusABC, node: int, index: int, sub: int = 0, timeout_s: float = 5.0) -> bytes:
    """An expedited SDO upload request; the server's answer frame (data)."""
    bus.send(can.Message(arbitration_id=0x600 + node, is_extended_id=False,
                         data=bytes((0x40, index & 0xFF, index >> 8, sub, 0, 0, 0, 0))))
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        try:
            msg = bus.recv(0.2)
        except can.CanOperationError:  # (the master hears the malformed datagrams too)
            continue
        if msg is not None and msg.arbitration_id == 0x580 + node:
            return bytes(msg.data)
    raise AssertionError(f"no SDO answer from node {node}")


@pytest.mark.parametrize("options", [["--bitrate", "1000000"], ["--bitrate", "0"], ["--latency-probe", "probe.npz"]],
                         ids=["bitrate", "no-bitrate", "receive-thread"])
def test_every_malformed_datagram_is_counted_and_dropped_and_serve_keeps_serving(tmp_path, options):
    """With the bit-rate emulation, without it, and with a receive thread (--latency-probe: python-can's
    Notifier reads the bus instead of the runtime's loop)."""
    out = tmp_path / "serve.json"
    options = [str(tmp_path / o) if o.endswith(".npz") else o for o in options]
    with served(*options, "--json", str(out)) as srv:
        master = can.Bus(**srv.bus_kwargs())
        raw = _sender(srv.group, srv.port)
        try:
            assert _sdo_read(master, 1, 0x1000)[0] == 0x43
            for datagram in MALFORMED.values():
                raw.send(datagram)
            raw.send(ERROR_FRAME)
            for datagram in UNROUTED:
                raw.send(datagram)
            time.sleep(0.3)
            # still serving: SDO answered, and the 0x2100:1 malformed frames counter reads every datagram
            assert _sdo_read(master, 1, 0x1000)[0] == 0x43
            answer = _sdo_read(master, 1, 0x2100, 1)
            assert answer[0] == 0x43 and int.from_bytes(answer[4:8], "little") == len(MALFORMED)
        finally:
            raw.close()
            master.shutdown()
        code = srv.stop()
    assert code == 0, srv.stderr
    assert "Traceback" not in srv.stderr
    report = json.loads(out.read_text())
    rt = report["runtime"]
    assert rt["thread_error"] == "" and report["healthy"]
    assert rt["frames_malformed"] == len(MALFORMED), rt
    assert rt["error_frames"] == 1
    assert rt["frames_unrouted"] >= len(UNROUTED)
    assert rt["frames_received"] == (rt["frames_routed"] + rt["frames_unrouted"] + rt["error_frames"]
                                     + rt["frames_malformed"])
    canopen = report["axes"][0]["canopen"]
    assert canopen["malformed_frames"] == len(MALFORMED)
    assert canopen["internal_errors"] == 0


@pytest.mark.parametrize("name", sorted(MALFORMED))
def test_decode_names_what_is_malformed(name):
    with pytest.raises(MalformedFrame) as err:
        decode_datagram(MALFORMED[name], 1.0)
    assert str(err.value)


def test_well_formed_frames_decode_and_pass_the_check():
    for datagram in [_packed(), ERROR_FRAME, *UNROUTED,
                     _packed(arbitration_id=0x1FFFFFFF, is_extended_id=True, dlc=0, data=b"")]:
        msg, channel = decode_datagram(datagram, 1.0)
        assert frame_problem(msg) is None and channel == "test" and msg.timestamp == 1.0


def test_bus_load_never_exceeds_the_bit_rate(tmp_path):
    """Frames delivered far faster than 125 kbit/s carries them (a host-local bus has no wire): the load,
    its peak and its mean stay at most 100 %; the frames beyond what the wire holds are counted."""
    out = tmp_path / "serve.json"
    frame = _packed(arbitration_id=0x1F0, dlc=8, data=bytes(8))  # 8 bytes: ~1 ms each at 125 kbit/s
    with served("--bitrate", "125000", "--json", str(out)) as srv:
        raw = _sender(srv.group, srv.port)
        try:
            for _ in range(3):
                for _ in range(1000):
                    raw.send(frame)
                time.sleep(0.1)
            time.sleep(1.2)
        finally:
            raw.close()
        code = srv.stop()
    assert code == 0, srv.stderr
    bus = json.loads(out.read_text())["can_bus"]
    assert bus["frames_received"] >= 2000, bus  # (a few may be lost in the socket under load)
    assert 0 < bus["peak_load_percent"] <= 100.0, bus
    assert bus["load_percent"] <= 100.0 and bus["mean_load_percent"] <= 100.0, bus
    assert bus["frames_beyond_capacity"] > 0, bus


def test_a_slave_fed_by_its_own_notifier_counts_malformed_datagrams_as_malformed():
    """The CiA 301 stack on its own (docs/canopen-slave-api.md: ``slave.listener()`` in a python-can Notifier)
    on a udp_multicast bus: a malformed datagram is a malformed frame (0x2100:1), not an internal error."""
    from served_drive import private_group

    from virtualaxis.canopen_slave.slave import CanopenSlave
    from virtualaxis.drive.core import DEFAULT_EDS
    from virtualaxis.runtime.bus import open_bus

    group, port = private_group()
    bus = open_bus(f"udp_multicast:{group},port={port}")
    slave = CanopenSlave(bus, 5, DEFAULT_EDS)
    notifier = can.Notifier(bus, [slave.listener()], timeout=0.01)
    raw = _sender(group, port)
    try:
        for name in ("id 3.5", "not msgpack", "CAN FD frame", "dlc 8, 2 data bytes"):
            raw.send(MALFORMED[name])
        end = time.monotonic() + 5.0
        while slave.counters["malformed_frames"] < 4 and time.monotonic() < end:
            time.sleep(0.01)
        assert slave.counters["malformed_frames"] == 4
        assert slave.counters["internal_errors"] == 0
    finally:
        raw.close()
        notifier.stop()
        bus.shutdown()


@pytest.mark.parametrize("bitrate", [0, 1_000_000])
def test_frames_of_an_in_process_bus_are_checked_by_the_runtime(bitrate):
    """python-can's ``virtual`` bus hands over Message objects as their sender made them (``virtualaxis demo``,
    tests): the runtime checks them itself, counts the malformed ones and routes the rest; the bit-rate
    emulation gives them no bus time."""
    from test_drive_rig import seed_config, seed_discrete

    from virtualaxis.runtime import AxisNode, Runtime, open_bus
    from virtualaxis.runtime.bitrate import BitRateBus

    channel = f"frames-{bitrate}-{time.perf_counter_ns()}"
    bus = open_bus(f"virtual:{channel}")
    if bitrate:
        bus = BitRateBus(bus, bitrate)
    sender = can.Bus(interface="virtual", channel=channel)
    ax = AxisNode(bus, 1, seed_config(), discrete=seed_discrete())
    rt = Runtime(bus, [ax], lockstep=True, read_in_loop=False)
    bad = [can.Message(arbitration_id=3.5, is_extended_id=False, data=b"\x01"),
           can.Message(arbitration_id=0.0, is_extended_id=False, data=b"\x01\x01"),
           can.Message(arbitration_id=0x601, is_extended_id=False, data=b"\x40", dlc=8),
           can.Message(arbitration_id=0x900, is_extended_id=False, data=b""),
           can.Message(arbitration_id=0x601, is_extended_id=False, data=bytes(8), is_fd=True)]
    try:
        rt.open()
        for msg in bad:
            sender.send(msg)
        sender.send(can.Message(arbitration_id=0x601, is_extended_id=False,
                                data=bytes((0x40, 0x00, 0x10, 0, 0, 0, 0, 0))))
        end = time.monotonic() + 5.0
        while rt.stats.frames_received < len(bad) + 1 and time.monotonic() < end:
            time.sleep(0.01)
        rt.poll_once()
        st = rt.stats
        assert st.frames_malformed == len(bad) and st.frames_routed == 1, st
        assert ax.slave.counters["malformed_frames"] == len(bad)
        assert ax.slave.counters["sdo_requests"] == 1 and ax.slave.nmt_state.name == "PRE_OPERATIONAL"
        if bitrate:
            assert bus.stats()["frames_received"] == 1  # only the SDO request took bus time
    finally:
        rt.stop()
        sender.shutdown()
        bus.shutdown()
