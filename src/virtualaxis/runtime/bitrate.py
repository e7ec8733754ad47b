"""CAN bit-rate emulation on a served bus: frame transmission times, arbitration by identifier, bus load.

A python-can ``virtual`` or ``udp_multicast`` bus delivers a frame as fast as the host can; a real CAN bus at
1 Mbit/s needs ~47 + 8 x DLC bits plus stuff bits per classical frame (111-135 us for 8 data bytes) and, when
several frames wait, sends the one with the lowest identifier first. :class:`BitRateBus` wraps the served bus
so that a master that would overload a real bus sees the delays and the overload here:

- ``send`` queues the frame through a C queue (it never blocks the drive thread and costs it about what a send on
  the bare bus does). The frames are released by :meth:`BitRateBus.release_due`: called by a transmitter thread,
  or, after :meth:`BitRateBus.take_over`, by a loop that wakes on time anyway (the runtime's: no second thread's
  wake-up and interpreter-lock hand-over per frame). It works out the frame's length (compiled) and puts it on the
  wire on a virtual bus timeline: the frame starts when the
  bus is idle (after the previous frame of this node and after every frame received from other nodes), among
  the frames waiting at that moment the lowest identifier wins (arbitration), and it is handed to the wrapped
  bus when its last bit would have been sent (start + bits / bit rate). The release can be late by the host's
  wake-up latency (tens of us); the next frame then follows no sooner than its own frame time after it (as a
  receiver sees frames on a real bus), up to one frame time behind the timeline; beyond, the release catches up.
  The timeline itself is exact (no drift, no throughput lost to late wake-ups).
- Frame length: CAN 2.0A/B data or remote frame: SOF, arbitration field, control field, data, CRC-15, CRC
  delimiter, ACK, EOF and the 3-bit intermission; stuff bits either computed from the frame's actual bits
  (``stuffing="computed"``, the default: the CRC-15 is computed and every run of 5 equal bits from SOF to the
  CRC gets one stuff bit) or the worst case (``stuffing="worst"``: one per 4 bits after the first).
- Frames received from other nodes take bus time too: a frame ends at its receive timestamp, or right after the
  frames before it when a burst arrived at once (a sender that does not emulate its side hands its frames over
  faster than the wire carries them); it pushes the idle time of the timeline and counts in the bus load. A
  frame that is not a classical CAN frame (:func:`~virtualaxis.runtime.frames.frame_problem`) never was on the
  wire: it takes no bus time (the runtime counts it as malformed).
- Bus load: every frame (sent or received) occupies an interval of the wire as long as its bits; intervals
  never overlap (a received frame that ended, by its timestamp, while the wire was still busy is placed right
  after), so no window holds more bits than the bit rate carries: the load is at most 100 %. Frames that
  other nodes deliver faster than the bit rate could carry them (a host-local bus has no wire) queue up on
  the wire; those that would end more than :data:`LOAD_WINDOW_S` in the future are counted in
  ``frames_beyond_capacity`` instead.
- :meth:`stats`: bus load in percent of the bit rate over the last second and since the start, its peak
  (per 1 s window), frames and bits sent and received, the queueing delay of this node's frames (mean / max)
  and frames refused because the transmit queue was full (:data:`TX_QUEUE_LIMIT`; ``send`` then raises
  ``can.CanOperationError`` like a full controller buffer, which the CiA 301 stack counts as ``tx_errors``).
"""

from __future__ import annotations

import heapq
import itertools
import queue
import threading
import time
from collections import deque

import can
import numpy as np
from numba import njit

from virtualaxis import jitcache  # noqa: F401 - numba's cache errors made non-fatal
from virtualaxis.runtime.frames import frame_problem

#: frames waiting for the bus beyond which ``send`` refuses (a controller's transmit buffer) [frames]
TX_QUEUE_LIMIT = 1024
#: window of the "current" bus load [s]
LOAD_WINDOW_S = 1.0
_CRC15_POLY = 0x4599


@njit(cache=True, nogil=True, inline="always")
def _put_bits(seq: np.ndarray, n: int, value: int, count: int) -> int:
    """The ``count`` low bits of ``value``, most significant first, into ``seq`` from ``n``; the next free index."""
    for i in range(count - 1, -1, -1):
        seq[n] = (value >> i) & 1
        n += 1
    return n


@njit(cache=True, nogil=True)
def _frame_bits_kernel(ident: int, extended: bool, remote: bool, dlc: int, n_data: int, data_hi: int,
                       data_lo: int, worst: bool) -> int:
    """Bits of a classical CAN frame from its fields (``data_hi`` / ``data_lo``: the first / last four data
    bytes, big-endian, zero-padded): the bits from SOF to the CRC laid out one by one, the CRC-15 shifted
    through them, one stuff bit after every 5 equal bits (the stuff bit starts the next run), then CRC
    delimiter, ACK slot and delimiter, EOF and intermission. Compiled without the GIL: the transmitter thread
    works it out while the runtime thread runs."""
    seq = np.empty(128, np.uint8)
    rtr = 1 if remote else 0
    n = _put_bits(seq, 0, 0, 1)  # SOF
    if extended:  # base id, SRR, IDE, id extension, RTR, r1, r0
        n = _put_bits(seq, n, (ident >> 18) & 0x7FF, 11)
        n = _put_bits(seq, n, 0b11, 2)
        n = _put_bits(seq, n, ident & 0x3FFFF, 18)
        n = _put_bits(seq, n, rtr << 2, 3)
    else:  # id, RTR, IDE, r0
        n = _put_bits(seq, n, ident & 0x7FF, 11)
        n = _put_bits(seq, n, rtr << 2, 3)
    n = _put_bits(seq, n, dlc, 4)
    n = _put_bits(seq, n, data_hi >> (8 * (4 - min(n_data, 4))), 8 * min(n_data, 4))
    if n_data > 4:
        n = _put_bits(seq, n, data_lo >> (8 * (8 - n_data)), 8 * (n_data - 4))
    crc = 0
    for k in range(n):
        feedback = seq[k] ^ ((crc >> 14) & 1)
        crc = (crc << 1) & 0x7FFF
        if feedback:
            crc ^= _CRC15_POLY
    n = _put_bits(seq, n, crc, 15)
    if worst:
        stuff = (n - 1) // 4
    else:
        stuff = 0
        run = 0
        last = 2
        for k in range(n):
            b = seq[k]
            run = run + 1 if b == last else 1
            last = b
            if run == 5:
                stuff += 1
                last = 1 - b
                run = 1
    return n + stuff + 1 + 2 + 7 + 3  # CRC delimiter, ACK slot + delimiter, EOF, intermission


#: frame_bits results kept for frames seen before (SYNC, heartbeat, SDO, a drive at rest) [entries]
_CACHE_LIMIT = 4096
_cache: dict[tuple, int] = {}


def frame_bits(msg: can.Message, stuffing: str = "computed") -> int:
    """Bits a classical CAN frame occupies on the bus, intermission (3 bits) included."""
    dlc = min(msg.dlc, 8)
    n_data = 0 if msg.is_remote_frame else dlc
    data = bytes(msg.data[:n_data])
    key = (msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame, dlc, data, stuffing)
    cached = _cache.get(key)
    if cached is not None:
        return cached
    padded = int.from_bytes(data.ljust(8, b"\x00"), "big")
    ident = msg.arbitration_id & (0x1FFFFFFF if msg.is_extended_id else 0x7FF)
    bits = _frame_bits_kernel(ident, bool(msg.is_extended_id), bool(msg.is_remote_frame), dlc, len(data),
                              padded >> 32, padded & 0xFFFFFFFF, stuffing == "worst")
    if len(_cache) >= _CACHE_LIMIT:
        _cache.clear()
    _cache[key] = bits
    return bits


#: a receive timestamp at most this old is taken as the end of the frame on the wire [s] (older, or on another
#: clock: the moment the frame is handled)
RX_STAMP_TRUST_S = 5.0


class BitRateBus(can.BusABC):
    """Wraps a bus with the timing of a CAN bus at ``bitrate`` bit/s (see the module doc)."""

    def __init__(self, inner: can.BusABC, bitrate: int = 1_000_000, *, stuffing: str = "computed",
                 tx_queue_limit: int = TX_QUEUE_LIMIT):
        if not isinstance(bitrate, int) or not 10_000 <= bitrate <= 1_000_000:
            raise ValueError(f"CAN bit rate must be 10000..1000000 bit/s (got {bitrate!r})")
        if stuffing not in ("computed", "worst"):
            raise ValueError(f"stuffing must be 'computed' or 'worst' (got {stuffing!r})")
        self.inner = inner
        self.bitrate = bitrate
        self.stuffing = stuffing
        self.tx_queue_limit = tx_queue_limit
        self.channel_info = f"{getattr(inner, 'channel_info', 'bus')} at {bitrate} bit/s"
        super().__init__(channel=None)
        #: the timeline, the wire and the counters; held only for a few assignments (a plain lock: the
        #: transmitter is woken by ``_inbox``, not by this lock)
        self._lock = threading.Lock()
        #: frames handed over by send(), in the order they were queued: (priority, seq, queued_s, msg); the
        #: transmitter thread alone takes them (a C queue: a put is a fraction of a microsecond and wakes the
        #: transmitter only if it waits). ``_pending``: taken from the inbox, not yet among the ready frames;
        #: ``_ready``: a heap of the frames that were waiting when the bus last went idle (arbitration among
        #: them: the lowest identifier). O(1) / O(log n) per frame: a linear scan of a backlog under a lock
        #: that send() needs too would block the runtime's send() and let the backlog grow
        self._inbox: queue.SimpleQueue = queue.SimpleQueue()
        self._pending: deque[tuple[int, int, float, can.Message]] = deque()
        self._ready: list[tuple[int, int, float, can.Message]] = []
        self._sent_count = itertools.count(1)  # next(): atomic in CPython, from any sending thread
        self._done = 0  # frames taken off the transmit queue (sent or refused by the wrapped bus); transmitter only
        self._idle_s = time.perf_counter()   # the bus timeline: when the last frame (any node) ended
        #: frames on the wire (load accounting): (start, end, bits), non-overlapping, in order; the last
        #: LOAD_WINDOW_S and any still ahead of the present
        self._window: deque[tuple[float, float, int]] = deque()
        self._t0 = time.perf_counter()
        self._wire_end_s = self._t0  # end of the last frame on the wire
        self._wire_bits = 0  # bits of every frame put on the wire
        self.frames_beyond_capacity = 0
        #: the wrapped bus checks every frame it delivers (runtime.frames); else they are checked here
        self.checks_frames = bool(getattr(inner, "checks_frames", False))
        self.frames_tx = self.frames_rx = self.bits_tx = self.bits_rx = 0
        self._inner_refused = 0  # frames the wrapped bus refused; the transmitter's count
        self._full_refused = 0  # frames send() refused (queue full); the sending threads' count
        self.queue_max = 0
        self.delay_sum_s = 0.0
        self.delay_max_s = 0.0
        self.peak_load = 0.0
        self._peak_checked_s = self._t0
        self._stop = False
        #: the frame on the wire now: (end, bits, queued_s, msg), chosen and not yet handed to the wrapped bus
        self._in_flight: tuple[float, int, float, can.Message] | None = None
        self._driven = False  # a caller of take_over() releases the frames, not the transmitter thread
        self._last_release_s = -1.0  # when the last frame was handed to the wrapped bus (the caller's clock)
        _frame_bits_kernel(0, False, False, 0, 0, 0, 0, False)  # compiled (or loaded) now, not at the first frame
        self._start_transmitter()

    # ------------------------------------------------------------------ python-can interface
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Queue ``msg`` for the wire (never blocks); ``can.CanOperationError`` when :attr:`tx_queue_limit`
        frames already wait. Its length and priority are worked out by the transmitter thread, off the
        sender's path."""
        seq = next(self._sent_count)
        waiting = seq - 1 - self._done - self._full_refused
        if waiting >= self.tx_queue_limit:
            self._full_refused += 1
            raise can.CanOperationError("CAN transmit queue full (bus overloaded)")
        if waiting + 1 > self.queue_max:
            self.queue_max = waiting + 1
        priority = ((msg.arbitration_id & 0x1FFFFFFF) << 1) if msg.is_extended_id else \
            ((msg.arbitration_id & 0x7FF) << 19)   # an 11-bit id beats an extended one with the same base id
        self._inbox.put((priority, seq, time.perf_counter(), msg))

    @property
    def tx_refused(self) -> int:
        """Frames not sent: refused by :meth:`send` (queue full) or by the wrapped bus."""
        return self._full_refused + self._inner_refused

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        msg = self.inner.recv(timeout)
        if msg is not None:
            self._took_bus(msg)
        return msg, False

    def _took_bus(self, msg: can.Message) -> None:
        """A frame received from another node: it took the bus for its bits before it ended, at its receive
        timestamp (timeline, load). Placed at the moment it is handled instead, the frames that wait in the
        socket while this process is stalled made a backlog the wire never had: with the default 1 Mbit/s, two
        CSP axes at 1 ms SYNC (25 % load) then queued their TPDOs for seconds after a 1 s stall of ``serve``."""
        if not self.checks_frames and frame_problem(msg) is not None:
            return  # (no frame on the wire; the runtime counts it as malformed)
        bits = frame_bits(msg, self.stuffing)
        now = time.perf_counter()
        end = now
        stamp = msg.timestamp
        if stamp:  # the receive timestamp (time.time() clock) on the perf_counter timeline, never in the future
            on_timeline = stamp - time.time() + now
            if now - RX_STAMP_TRUST_S <= on_timeline <= now:
                end = on_timeline
        with self._lock:
            self.frames_rx += 1
            self.bits_rx += bits
            # on the wire after the frames before it (a master that does not emulate its side hands over a burst
            # at once: its frames were on the wire one after the other, the last one ends after them all)
            placed = self._account(end, bits, now)
            if placed is None:
                placed = end
            if placed > self._idle_s:  # (a frame that ended before the bus fell idle only counts for the load)
                self._idle_s = placed

    def fileno(self) -> int:
        return self.inner.fileno()

    def drain(self, limit: int, on_error=None) -> list[can.Message]:
        """The wrapped bus's waiting frames at once (its ``drain``, else ``recv(0)`` in turn), each taking
        its bus time as in :meth:`_recv_internal`."""
        inner_drain = getattr(self.inner, "drain", None)
        if inner_drain is not None:
            frames = inner_drain(limit, on_error)
        else:
            frames = []
            for _ in range(limit):
                msg = self.inner.recv(0.0)
                if msg is None:
                    break
                frames.append(msg)
        for msg in frames:
            self._took_bus(msg)
        return frames

    def shutdown(self) -> None:
        self._stop = True
        self._inbox.put(None)  # (wakes the transmitter)
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self.inner.shutdown()
        super().shutdown()

    # ------------------------------------------------------------------ the wire
    def _account(self, end_s: float, bits: int, now: float) -> float | None:
        """A frame of ``bits`` that ended at ``end_s`` on the wire (load): placed after the previous frame if
        they would overlap (see the module doc); returns where it ends on the wire (None: beyond capacity, not
        placed); under the lock."""
        duration = bits / self.bitrate
        end = max(end_s, self._wire_end_s + duration, self._t0 + duration)
        if end > now + LOAD_WINDOW_S:
            self.frames_beyond_capacity += 1
            return None
        self._wire_end_s = end
        self._wire_bits += bits
        window = self._window
        window.append((end - duration, end, bits))
        horizon = now - LOAD_WINDOW_S
        while window and window[0][0] < horizon:
            window.popleft()
        if now - self._peak_checked_s >= 0.1:   # peak of the 1 s load, sampled every 0.1 s
            self._peak_checked_s = now
            if now - self._t0 >= LOAD_WINDOW_S:
                self._load_at(now)
        return end

    def _load_at(self, now: float) -> float:
        """Fraction of the last :data:`LOAD_WINDOW_S` before ``now`` (since the start, if shorter) the wire
        was busy: the frames that lie wholly inside it; under the lock."""
        since = max(now - LOAD_WINDOW_S, self._t0)
        bits = sum(b for start, end, b in self._window if start >= since and end <= now)
        load = bits / (self.bitrate * max(now - since, 1e-3))
        if load > self.peak_load:  # (every load reported or sampled: the peak never reads below one shown)
            self.peak_load = load
        return load

    def _take_inbox(self, block: bool) -> None:
        """Move the frames handed over by send() to ``_pending`` (``block``: wait up to 0.1 s for one)."""
        inbox, pending = self._inbox, self._pending
        if not block and inbox.empty():
            return
        try:
            if block:
                item = inbox.get(timeout=0.1)
                if item is None:
                    return
                pending.append(item)
            while True:
                item = inbox.get_nowait()
                if item is not None:
                    pending.append(item)
        except queue.Empty:
            return

    def release_due(self, now: float) -> float | None:
        """Hand every frame whose last bit has passed at ``now`` (``time.perf_counter``) to the wrapped bus;
        returns when the next waiting frame is due (``None``: none waits). Called by one thread at a time: the
        transmitter thread, or the thread that took the transmission over (:meth:`take_over`).

        The bus goes idle at ``start`` (the end of the last frame, or the queueing of the first frame after an
        idle bus); among the frames queued by then, the lowest identifier wins (arbitration) and its last bit
        passes ``bits / bitrate`` later. The choice is made once: a frame queued after ``start`` waits for the
        next round, as on the wire. A frame is released no sooner than its own frame time after the previous
        one (a receiver of a real bus never sees two frames closer together): a late release delays the next
        by as much, up to one frame time behind the timeline."""
        self._take_inbox(block=False)
        pending, ready = self._pending, self._ready
        lock = self._lock
        while True:
            flight = self._in_flight
            if flight is None:
                if not pending and not ready:
                    return None
                with lock:
                    start = self._idle_s if ready else max(self._idle_s, pending[0][2])
                    while pending and pending[0][2] <= start:
                        heapq.heappush(ready, pending.popleft())
                    _prio, _seq, queued_s, msg = heapq.heappop(ready)
                    bits = frame_bits(msg, self.stuffing)
                    end = start + bits / self.bitrate
                    self._idle_s = end
                flight = self._in_flight = (end, bits, queued_s, msg)
            end, bits, queued_s, msg = flight
            # a receiver sees this node's frames at least a frame time apart: a release that came late holds the
            # next frame back by as much, up to one frame time behind the timeline (beyond, it catches up: the
            # throughput stays the bit rate)
            frame_s = bits / self.bitrate
            due = self._last_release_s + frame_s
            due = end if due <= end else min(due, end + frame_s)
            if due > now:
                return due
            self._in_flight = None
            self._last_release_s = now
            try:
                self.inner.send(msg)
            except (can.CanError, OSError, ValueError):
                self._inner_refused += 1
                self._done += 1
                continue
            with lock:
                self._done += 1
                self.frames_tx += 1
                self.bits_tx += bits
                delay = end - queued_s
                self.delay_sum_s += delay
                if delay > self.delay_max_s:
                    self.delay_max_s = delay
                self._account(end, bits, time.perf_counter())

    def take_over(self) -> None:
        """From now on the calling thread releases the frames: it calls :meth:`release_due` in its own loop and
        waits no longer than until the time that returns (the transmitter thread stops). A runtime whose loop
        wakes on time anyway releases them on time without a second thread's wake-up per frame (and its
        interpreter lock hand-over). :meth:`hand_back` starts the transmitter thread again."""
        if self._driven:
            return
        self._driven = True
        self._inbox.put(None)  # (wakes the transmitter, which then stops)
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)

    def hand_back(self) -> None:
        """The transmitter thread releases the frames again (after :meth:`take_over`)."""
        if not self._driven or self._stop:
            return
        self._driven = False
        self._start_transmitter()

    @property
    def driven(self) -> bool:
        """Whether a caller of :meth:`take_over` releases the frames (else the transmitter thread)."""
        return self._driven

    def _start_transmitter(self) -> None:
        self._thread = threading.Thread(target=self._transmitter, name="can-bitrate-tx", daemon=True)
        self._thread.start()

    def _transmitter(self) -> None:
        perf = time.perf_counter
        sleep = time.sleep
        while not self._stop and not self._driven:
            due = self.release_due(perf())
            if due is None:
                self._take_inbox(block=True)
                continue
            remaining = due - perf()
            if remaining > 0:
                sleep(remaining)

    # ------------------------------------------------------------------ report
    def load(self) -> float:
        """Bus load over the last second [fraction of the bit rate, at most 1]."""
        now = time.perf_counter()
        with self._lock:
            return self._load_at(now)

    def stats(self) -> dict:
        """Bus load [%], frames, bits and this node's queueing delays [ms] (JSON-ready)."""
        now = time.perf_counter()
        elapsed = max(now - self._t0, 1e-3)
        with self._lock:
            load = self._load_at(now)
            wire_bits = self._wire_bits - sum(b for _start, end, b in self._window if end > now)
            return {
                "bitrate_bit_s": self.bitrate,
                "stuffing": self.stuffing,
                "load_percent": round(100.0 * load, 2),
                "peak_load_percent": round(100.0 * max(self.peak_load, load), 2),
                "mean_load_percent": round(100.0 * wire_bits / (self.bitrate * elapsed), 2),
                "frames_sent": self.frames_tx,
                "frames_received": self.frames_rx,
                "bits_sent": self.bits_tx,
                "bits_received": self.bits_rx,
                "tx_queue_max": self.queue_max,
                "tx_refused": self.tx_refused,
                "frames_beyond_capacity": self.frames_beyond_capacity,
                "tx_delay_mean_ms": round(1e3 * self.delay_sum_s / self.frames_tx, 4) if self.frames_tx else 0.0,
                "tx_delay_max_ms": round(1e3 * self.delay_max_s, 4),
            }
