"""CAN bit-rate emulation: frame lengths against the literature's formula, frame times and
arbitration order on a python-can virtual bus, bus load and a transmit queue that overflows, and `serve`
reporting the load of a master's traffic from another process."""

from __future__ import annotations

import contextlib
import json
import threading
import time

import can
import pytest
from served_drive import served

from virtualaxis.runtime.bitrate import BitRateBus, frame_bits

pytestmark = pytest.mark.exclusive  # timing-sensitive: background jobs stopped meanwhile


def _msg(cob: int, n: int, fill: int = 0x55, ext: bool = False, rtr: bool = False) -> can.Message:
    return can.Message(arbitration_id=cob, data=bytes([fill] * n) if not rtr else b"", dlc=n, is_extended_id=ext,
                       is_remote_frame=rtr)


@pytest.mark.parametrize("n", range(9))
def test_worst_case_frame_length_is_the_literature_formula(n):
    # Davis, Burns, Bril, Lukkien (2007), "Controller Area Network (CAN) schedulability analysis: refuted,
    # revisited and revised", eq. (1): C = (g + 8s + 13 + floor((g + 8s - 1) / 4)) bit times, g = 34 (11-bit) or
    # 54 (29-bit identifiers); the 13 fixed bits include the 3-bit inter-frame space.
    for ext, g in ((False, 34), (True, 54)):
        assert frame_bits(_msg(0x123, n, ext=ext), "worst") == g + 8 * n + 13 + (g + 8 * n - 1) // 4


def test_computed_stuffing_lies_between_none_and_worst_case():
    for n in range(9):
        for fill in (0x00, 0xFF, 0x55, 0x0F, 0x3C):
            m = _msg(0x7E0 if fill else 0x000, n, fill)
            bits = frame_bits(m)
            assert 47 + 8 * n <= bits <= frame_bits(m, "worst")
    # long runs of equal bits are stuffed, alternating bits are not: zeros need more bits than 0x55
    assert frame_bits(_msg(0x000, 8, 0x00)) > frame_bits(_msg(0x2AA, 8, 0x55)) + 10
    assert frame_bits(_msg(0x123, 0, rtr=True)) < frame_bits(_msg(0x123, 8))


class _Arrivals(can.Listener):
    def __init__(self):
        self.got: list[tuple[float, int]] = []
        self.cond = threading.Condition()

    def on_message_received(self, msg: can.Message) -> None:
        with self.cond:
            self.got.append((time.perf_counter(), msg.arbitration_id))
            self.cond.notify_all()

    def wait(self, n: int, timeout_s: float = 5.0) -> list[tuple[float, int]]:
        end = time.monotonic() + timeout_s
        with self.cond:
            while len(self.got) < n and time.monotonic() < end:
                self.cond.wait(0.05)
            return list(self.got)


def test_frame_times_and_arbitration_order_at_125_kbit(request):
    channel = f"va-bitrate-{id(request)}"
    tx = BitRateBus(can.Bus(interface="virtual", channel=channel), 125_000)
    rx = can.Bus(interface="virtual", channel=channel)
    arrivals = _Arrivals()
    notifier = can.Notifier(rx, [arrivals], timeout=0.01)
    try:
        frames = [_msg(cob, 8) for cob in (0x500, 0x400, 0x300, 0x200, 0x181, 0x182, 0x183, 0x100 + 0x7F)]
        t0 = time.perf_counter()
        for m in frames:
            tx.send(m)
        got = arrivals.wait(len(frames))
        assert len(got) == len(frames)
        ids = [cob for _t, cob in got]
        # the first frame found the bus idle and went at once; the rest waited and won by identifier
        assert ids[0] == 0x500 and ids[1:] == sorted(ids[1:])
        expected_s = sum(frame_bits(m) for m in frames) / 125_000
        took = got[-1][0] - t0
        assert 0.95 * expected_s <= took <= expected_s + 0.05, (took, expected_s)
        # never early: the k-th frame arrives no sooner than the bits of the frames before it and its own take
        # (late releases on a loaded host are allowed; the timeline stays exact)
        by_id = {m.arbitration_id: m for m in frames}
        cum = 0
        for t, cob in got:
            cum += frame_bits(by_id[cob])
            assert t - t0 >= cum / 125_000 - 1e-4, (cob, t - t0, cum / 125_000)
        s = tx.stats()
        assert s["frames_sent"] == len(frames) and s["tx_queue_max"] >= len(frames) - 1
        assert s["tx_delay_max_ms"] >= 0.9 * 1e3 * expected_s * (len(frames) - 1) / len(frames)
    finally:
        notifier.stop()
        tx.shutdown()
        rx.shutdown()


def test_bus_load_and_overload(request):
    channel = f"va-bitrate-load-{id(request)}"
    tx = BitRateBus(can.Bus(interface="virtual", channel=channel), 500_000)
    try:
        # ~50 % load: one 8-byte frame (111..135 bits) every 0.25 ms at 500 kbit/s
        end = time.perf_counter() + 0.6
        n = 0
        t = time.perf_counter()
        while t < end:
            tx.send(_msg(0x181, 8, 0x55))
            n += 1
            t += 0.25e-3
            while time.perf_counter() < t:
                time.sleep(0)
        time.sleep(0.05)
        bits = frame_bits(_msg(0x181, 8, 0x55))
        s = tx.stats()
        assert s["frames_sent"] == n and s["tx_refused"] == 0
        expected = 100.0 * bits / 500_000 / 0.25e-3
        assert 0.6 * expected <= s["load_percent"] <= 1.1 * expected, (s, expected)
        # a burst the bus cannot carry: the transmit queue fills, send refuses like a full controller buffer
        tx.tx_queue_limit = 64
        refused = 0
        for _ in range(300):
            try:
                tx.send(_msg(0x182, 8))
            except can.CanOperationError:
                refused += 1
        assert refused > 0 and tx.stats()["tx_refused"] == refused
    finally:
        tx.shutdown()


def test_serve_reports_the_bus_load_of_a_master_in_another_process(tmp_path):
    """A master with its own 125 kbit/s emulation floods 8-byte frames: its sends are paced by the bus (and
    refused once its queue is full); `serve` at 125 kbit/s reports a load near 100 %."""
    from virtualaxis.master import connect

    out = tmp_path / "serve.json"
    with served("--bitrate", "125000", "--json", str(out)) as srv:
        net = connect(srv.spec, bitrate=125_000)
        try:
            t0 = time.perf_counter()
            sent = refused = 0
            while time.perf_counter() - t0 < 1.0:
                try:
                    net.bus.send(_msg(0x1F0, 8))
                    sent += 1
                except can.CanOperationError:
                    refused += 1
                    time.sleep(1e-3)
            time.sleep(0.3)
            bitrate_bus = net.bus
        finally:
            net.disconnect()  # (the queue keeps draining until the bus is shut down)
        master = bitrate_bus.stats()
    assert refused > 0 and master["tx_delay_max_ms"] > 100  # the master saw the bus was full
    bits = frame_bits(_msg(0x1F0, 8))
    assert master["mean_load_percent"] <= 101.0  # the master never put more on the bus than it carries
    assert master["bits_sent"] == master["frames_sent"] * bits
    bus = json.loads(out.read_text())["can_bus"]
    assert bus["bitrate_bit_s"] == 125_000
    assert 60.0 <= bus["peak_load_percent"] <= 115.0, bus
    assert 0.95 * master["frames_sent"] <= bus["frames_received"] <= master["frames_sent"] + 5


def _reference_frame_bits(msg: can.Message, stuffing: str) -> int:
    """The frame length bit by bit, straight from the CAN 2.0 frame layout (a list of bits, CRC-15 shifted
    bit by bit, every run of 5 equal bits followed by an opposite stuff bit): the reference the integer /
    table-driven ``frame_bits`` must equal."""
    def bits_of(v: int, n: int) -> list[int]:
        return [(v >> (n - 1 - i)) & 1 for i in range(n)]

    dlc = min(msg.dlc, 8)
    rtr = 1 if msg.is_remote_frame else 0
    if msg.is_extended_id:
        ident = msg.arbitration_id
        seq = [0] + bits_of(ident >> 18, 11) + [1, 1] + bits_of(ident & 0x3FFFF, 18) + [rtr, 0, 0]
    else:
        seq = [0] + bits_of(msg.arbitration_id, 11) + [rtr, 0, 0]
    seq += bits_of(dlc, 4)
    for byte in (b"" if rtr else bytes(msg.data[:dlc])):
        seq += bits_of(byte, 8)
    crc = 0
    for b in seq:
        feedback = b ^ (crc >> 14)
        crc = (crc << 1) & 0x7FFF
        if feedback:
            crc ^= 0x4599
    seq += bits_of(crc, 15)
    if stuffing == "worst":
        stuff = (len(seq) - 1) // 4
    else:
        stuff, run, last = 0, 0, -1
        for b in seq:
            run = run + 1 if b == last else 1
            last = b
            if run == 5:
                stuff += 1
                last, run = 1 - b, 1
    return len(seq) + stuff + 13


def test_frame_bits_equals_the_bit_by_bit_reference_on_random_and_pathological_frames():
    import random

    rng = random.Random(7)
    patterns = [None, 0x00, 0xFF, 0x55, 0xF0, 0x0F, 0xE0, 0x1F, 0x07, 0x83]
    for _ in range(4000):
        ext = rng.random() < 0.3
        n = rng.randint(0, 8)
        rtr = rng.random() < 0.1
        pat = rng.choice(patterns)
        data = bytes(rng.getrandbits(8) if pat is None else pat for _ in range(n))
        ident = rng.choice([0, 0x1FFFFFFF if ext else 0x7FF, rng.getrandbits(29 if ext else 11)])
        msg = can.Message(arbitration_id=ident, is_extended_id=ext, is_remote_frame=rtr, dlc=n,
                          data=None if rtr else data)
        for stuffing in ("computed", "worst"):
            assert frame_bits(msg, stuffing) == _reference_frame_bits(msg, stuffing), (msg, stuffing)
            assert frame_bits(msg, stuffing) == _reference_frame_bits(msg, stuffing)  # (the cached answer too)


def test_frames_received_during_a_stall_take_the_bus_when_they_were_on_the_wire(request):
    """Another node's frames that wait in the socket while this process is stalled were on the wire at their
    receive timestamps, not when they are finally handled: after a 0.3 s stall with 400 frames waiting (each
    ~0.1 ms at 1 Mbit/s, 40 ms in all, spread over the 0.3 s), a frame sent right after the drain leaves at
    once. (Before, the 400 frames were stacked on the bus timeline after the stall, 40 ms of a backlog the
    wire never had; with serve stalling on a loaded host, two CSP axes at 25 % load queued for seconds. Found
    by a docs-only tester.)"""
    channel = f"va-bitrate-stall-{id(request)}"
    rx = BitRateBus(can.Bus(interface="virtual", channel=channel), 1_000_000)
    other = can.Bus(interface="virtual", channel=channel)
    try:
        for _ in range(400):
            other.send(_msg(0x201, 8, 0x55))
            time.sleep(0.3 / 400)
        time.sleep(0.02)  # the stall: nothing handled until now
        frames = rx.drain(1000)
        assert len(frames) == 400
        rx.send(_msg(0x181, 2))
        time.sleep(0.05)
        s = rx.stats()
        assert s["frames_sent"] == 1 and s["frames_received"] == 400
        assert s["tx_delay_max_ms"] < 5.0, s  # before: ~45 ms behind the phantom backlog
        assert 0.5 * 400 * frame_bits(_msg(0x201, 8, 0x55)) <= s["bits_received"]
    finally:
        rx.shutdown()
        other.shutdown()


def test_a_backlog_drains_at_the_bit_rate(request):
    """The transmitter picks the next frame from a heap: picking it by a scan of the whole queue (under the
    lock that send() needs too) cost more than a frame's time once a backlog had formed, so the backlog grew
    (a docs-only tester's two CSP axes at 55 % load: tx delays of seconds, the runtime thread a third of its
    time waiting for that lock). 3000 frames queued at once leave in their bus time (+ 30 %), and a send
    meanwhile does not wait."""
    channel = f"va-bitrate-backlog-{id(request)}"
    bus = BitRateBus(can.Bus(interface="virtual", channel=channel), 1_000_000, tx_queue_limit=5000)
    try:
        msgs = [_msg(0x181 + (k % 7), 8, k & 0xFF) for k in range(3000)]
        wire_s = sum(frame_bits(m) for m in msgs) / 1_000_000
        clock = time.pthread_getcpuclockid(bus._thread.ident)  # the transmitter thread's CPU time

        def drain(frames: list) -> tuple[float, float]:
            """(wall time, transmitter CPU per frame) to send ``frames`` queued at once."""
            sent0, cpu0, t0 = bus.stats()["frames_sent"], time.clock_gettime(clock), time.perf_counter()
            for m in frames:
                bus.send(m)
            while bus.stats()["frames_sent"] < sent0 + len(frames) and time.perf_counter() - t0 < 30:
                time.sleep(0.005)
            assert bus.stats()["frames_sent"] == sent0 + len(frames)
            return time.perf_counter() - t0, (time.clock_gettime(clock) - cpu0) / len(frames)

        small = min(drain(msgs[:5])[1] for _ in range(20))  # a queue of at most 5
        took, per_frame = drain(msgs)
        assert took < 1.3 * wire_s + 0.05, (took, wire_s)  # scanning: 0.67 s for 0.34 s of bus time here
        assert per_frame < 3 * small + 20e-6, (per_frame, small)  # the pick does not grow with the queue
        # a send while a backlog drains does not wait for the transmitter (scanning: up to 5 ms here)
        for m in msgs:
            bus.send(m)
        waits = []
        for m in msgs[:200]:
            t = time.perf_counter()
            bus.send(m)
            waits.append(time.perf_counter() - t)
            time.sleep(0.001)
        waits.sort()
        # the 99th percentile: one send of 200 may meet a preemption of this thread by the host (2.02 ms seen
        # once in CI), which says nothing about the transmitter
        assert waits[-3] < 2e-3, waits[-5:]
    finally:
        bus.shutdown()


@contextlib.contextmanager
def _taken_over(request, name: str, bitrate: int):
    """A bus whose frames the test releases by hand (``take_over``, then ``release_due``) and a second node on its
    channel."""
    channel = f"va-bitrate-{name}-{id(request)}"
    tx = BitRateBus(can.Bus(interface="virtual", channel=channel), bitrate)
    other = can.Bus(interface="virtual", channel=channel)
    try:
        tx.take_over()
        yield tx, other
    finally:
        tx.shutdown()
        other.shutdown()


def test_a_thread_that_took_the_transmission_over_releases_each_frame_at_its_wire_time(request):
    with _taken_over(request, "driven", 125_000) as (tx, rx):
        assert tx.driven
        frames = {cob: _msg(cob, 8, fill) for cob, fill in ((0x500, 0x11), (0x300, 0x22), (0x181, 0x33))}
        t_sent = time.perf_counter()
        for m in frames.values():
            tx.send(m)
        assert rx.recv(0.05) is None  # (no thread releases them now: 50 ms, the bus carries one frame per ms)
        # the first frame found the bus idle: its last bit passes bits / bit rate after it was queued
        due = tx.release_due(t_sent)
        assert due is not None and rx.recv(0.05) is None
        assert tx.release_due(due - 1e-6) == due and rx.recv(0.05) is None  # not a microsecond early
        nxt = tx.release_due(due)
        assert rx.recv(0.5).arbitration_id == 0x500
        # the two others waited for the idle bus: the lower identifier won, right after the first frame
        assert nxt == pytest.approx(due + frame_bits(frames[0x181]) / 125_000, abs=1e-12)
        assert rx.recv(0.05) is None
        assert tx.release_due(nxt + 1.0) is None  # (a caller that comes late releases every frame due by then)
        assert [rx.recv(0.5).arbitration_id for _ in range(2)] == [0x181, 0x300]
        assert tx.stats()["frames_sent"] == 3
        # handed back: the transmitter thread releases the frames again
        tx.hand_back()
        assert not tx.driven
        tx.send(_msg(0x182, 2))
        got = rx.recv(2.0)
        assert got is not None and got.arbitration_id == 0x182


def test_the_runtime_releases_the_emulated_frames_in_its_own_loop_while_it_runs(request):
    from test_drive_rig import seed_config, seed_discrete

    from virtualaxis.runtime import AxisNode, Runtime

    channel = f"va-bitrate-runtime-{id(request)}"
    bus = BitRateBus(can.Bus(interface="virtual", channel=channel), 1_000_000)
    master = can.Bus(interface="virtual", channel=channel)
    rt = Runtime(bus, [AxisNode(bus, 5, seed_config(), discrete=seed_discrete(), name="A5")])
    rt.start()
    try:
        end = time.monotonic() + 5.0
        while not bus.driven:
            assert time.monotonic() < end, "the runtime did not take the transmission over"
            time.sleep(0.005)
        sent = bus.stats()["frames_sent"]
        for _ in range(20):  # SDO upload of 0x1000 (device type): each answer is released by the runtime's loop
            master.send(can.Message(arbitration_id=0x605, data=b"\x40\x00\x10\x00\x00\x00\x00\x00",
                                    is_extended_id=False))
            end = time.monotonic() + 2.0
            while True:
                msg = master.recv(max(0.0, end - time.monotonic()))
                assert msg is not None, "no SDO answer"
                if msg.arbitration_id == 0x585:
                    break
            assert msg.data[0] == 0x43 and msg.data[1:4] == b"\x00\x10\x00"
        assert bus.stats()["frames_sent"] >= sent + 20
    finally:
        rt.stop()
    try:
        assert not bus.driven  # handed back when the loop ended: the bus's thread releases its frames again
        bus.send(can.Message(arbitration_id=0x185, data=b"\x01", is_extended_id=False))
        end = time.monotonic() + 2.0
        while (got := master.recv(max(0.0, end - time.monotonic()))) is not None and got.arbitration_id != 0x185:
            pass  # (heartbeats and the like sent before it)
        assert got is not None
    finally:
        master.shutdown()
        bus.shutdown()


def test_a_late_release_holds_the_next_frame_back_by_as_much_up_to_one_frame_time(request):
    """A receiver of a real bus never sees two frames closer than the second one's frame time: when a release
    comes late, the next frame follows a frame time after it (a docs-only tester measured TPDOs of one SYNC 23-85 us
    apart at 1 Mbit/s, where each takes ~100 us); further behind the timeline than one frame time it catches up."""
    with _taken_over(request, "spacing", 125_000) as (tx, rx):
        frames = [_msg(0x181, 8, 0x11), _msg(0x182, 8, 0x22), _msg(0x183, 8, 0x33), _msg(0x184, 8, 0x44)]
        dur = [frame_bits(m) / 125_000 for m in frames]
        t_sent = time.perf_counter()
        for m in frames:
            tx.send(m)
        end1 = tx.release_due(t_sent)
        late = 0.4 * dur[1]  # the first release comes late by less than a frame time
        second = tx.release_due(end1 + late)
        assert rx.recv(0.5).arbitration_id == 0x181
        end2 = end1 + dur[1]  # (where the second frame ends on the timeline)
        assert second == pytest.approx(end1 + late + dur[1], abs=1e-9) and second > end2
        # further behind (the second release 1.5 frame times after its end): the third frame follows one frame time
        # behind the timeline, not a frame time after that release
        third = tx.release_due(end2 + 1.5 * dur[1])
        assert rx.recv(0.5).arbitration_id == 0x182
        end3 = end2 + dur[2]
        assert third == pytest.approx(end3 + dur[2], abs=1e-9) and third < end2 + 1.5 * dur[1] + dur[2]
        assert tx.release_due(third) is not None and rx.recv(0.5).arbitration_id == 0x183
        # a caller that comes very late releases what is due at once (the throughput stays the bit rate)
        assert tx.release_due(third + 1.0) is None and rx.recv(0.5).arbitration_id == 0x184


def test_a_burst_handed_over_at_once_takes_the_wire_one_frame_after_the_other(request):
    """A master that does not emulate its side hands five RPDOs and a SYNC over at once; on the wire they ran one
    after the other, so this node's answer starts after the last of them ends (a docs-only tester saw answers
    at 125 kbit/s sooner than the SYNC and the TPDO take on the wire)."""
    with _taken_over(request, "burst", 125_000) as (tx, master):
        burst = [_msg(0x201 + k, 8, 0x5A) for k in range(5)] + [_msg(0x080, 0)]
        burst_s = sum(frame_bits(m) for m in burst) / 125_000  # ~5.5 ms
        for m in burst:
            master.send(m)
        for _ in burst:
            assert tx.recv(1.0) is not None  # (each takes its bus time as it is received)
        t_queued = time.perf_counter()
        answer = _msg(0x181, 6, 0x33)
        tx.send(answer)
        due = tx.release_due(t_queued)
        # the first frame of the burst ended at its receive time; the other five took their frame times after it
        assert due >= t_queued - 1e-3 + burst_s - frame_bits(burst[0]) / 125_000 + frame_bits(answer) / 125_000, \
            (due - t_queued, burst_s)


def test_the_peak_load_never_reads_below_a_load_already_reported(request):
    with _taken_over(request, "peak", 1_000_000) as (tx, _other):
        t0 = time.perf_counter()
        for k in range(60):  # ~7 ms of frames
            tx.send(_msg(0x181, 8, k))
        assert tx.release_due(t0 + 1.0) is None
        time.sleep(0.05)
        shown = tx.stats()["load_percent"]
        assert shown > 0.0
        time.sleep(1.1)  # the frames have left the 1 s window
        s = tx.stats()
        assert s["load_percent"] < shown and s["peak_load_percent"] >= shown, (s, shown)
