"""Every drive cycle's actual values and each axis' state for the live page, in shared memory.

One block per axis (:class:`PageBlock`) in a shared-memory segment that serve creates and the page's server
process (server.py) maps:

- **sample slots**: the drive's cycle hook (:meth:`PageBlock.hook`, runtime thread, under the drive's lock)
  packs the published output values of the cycle before (0x6062, 0x6064, 0x60F4, 0x606C, 0x6077, 0x6078, the
  cycle count) and the statusword into the next of :data:`HANDOFF_SLOTS` fixed slots, then the count of
  slots written: two ``pack_into`` calls, no object kept. A slot starts and ends with its sequence number
  (written first and last); the reader copies the ends before the values and the starts after them, so a
  slot is taken only if both equal the one expected (a slot the hook overwrote while it was read is dropped,
  never torn);
- **units**: the position factor and the rated torque / current, written by serve's state thread, with which
  the server process converts the raw values to SI units;
- **state**: the state message of the axis as JSON, written by serve's state thread under a sequence lock;
- **clients**: the live streams the server process has open on the axis (serve builds the state message ten
  times a second while there are any, once a second otherwise).

The server process (:class:`LongRing`) copies the slots since its last call in one NumPy step, drops those
the hook overwrote meanwhile (counted in :attr:`LongRing.lost`; a recording spanning them is refused),
converts them to SI units and appends them to a long ring of float64 rows (``seconds`` of drive cycles): the
scope streams from there and a recording is a slice of it, one row per drive cycle.

The hook runs at the start of a drive cycle: the values it stores are those published by the cycle before.
A row of the long ring holds one instant: the position loop's sample of a cycle (0x6062, 0x6064, 0x60F4) with
the velocity, torque and current at that cycle's start (published by the cycle before), as ``virtualaxis
simulate`` writes its traces.
"""

from __future__ import annotations

import json
import math
import struct
import threading

import numpy as np

#: columns of a ring row (SI units; statusword as a number)
COLUMNS = ("pos_cmd", "pos_fb", "following_error", "vel_meas", "torque_meas", "current_q", "statusword")
_STATUSWORD_KEY = (0x6041, 0)
HANDOFF_SLOTS = 1 << 14  # drive cycles the server process may fall behind (16 s at a 1 ms cycle)
HANDOFF_MARGIN = 1 << 10  # slots kept clear of the hook's writing position while draining
STATE_BYTES = 1 << 16  # room for one axis' state message (JSON)
STATE_READ_TRIES = 3  # reads of a state message that serve is writing meanwhile before the last whole one is taken

_U64 = struct.Struct("<Q")
_F64X3 = struct.Struct("<3d")
#: a slot: seq, statusword, 0x6062, 0x6064, 0x60F4, 0x606C, 0x6077, 0x6078, drive cycle count, seq
_SLOT = struct.Struct("<q8dq")
_SLOT_DTYPE = np.dtype([("seq", "<i8"), ("sw", "<f8"), ("v", "<f8", (7,)), ("end", "<i8")])
_SLOT_BYTES = _SLOT.size
_SLOT_MASK = HANDOFF_SLOTS - 1
_NAN_SLOT_VALUES = (math.nan,) * 8
# header words (8 bytes each)
_W_END, _CLIENTS, _STATE_SEQ, _STATE_LEN = 1, 2, 3, 4
_UNITS_AT = 8 * 5  # metres per position unit, rated torque [N m or N], rated current [A]
_HEADER_BYTES = 64
_STATE_AT = _HEADER_BYTES
_SLOTS_AT = _STATE_AT + STATE_BYTES
BLOCK_BYTES = _SLOTS_AT + HANDOFF_SLOTS * _SLOT.size
_RATED_CURRENT = 0x6075  # mA
_RATED_TORQUE = 0x6076  # mN m (N for a force actuator)


class RecordingError(ValueError):
    """A requested slice of the ring is not (or no longer) held; the message says why."""


def segment_size(n_axes: int) -> int:
    """Bytes of the shared-memory segment for ``n_axes`` blocks."""
    return BLOCK_BYTES * max(1, n_axes)


class PageBlock:
    """One axis' block of the segment ``buf`` (module doc); both processes use it, each its own side."""

    def __init__(self, buf: memoryview, axis: int):
        self.buf = buf
        self.base = axis * BLOCK_BYTES
        self._slots = self.base + _SLOTS_AT
        self._w_end = self.base + 8 * _W_END
        self._w = _U64.unpack_from(buf, self._w_end)[0]  # (serve's side: the next slot to write)
        self._pack_slot = _SLOT.pack_into
        self._pack_u64 = _U64.pack_into
        self._last_state = b""  # (the server process' side: the newest state message read whole)

    def _word(self, i: int) -> int:
        return _U64.unpack_from(self.buf, self.base + 8 * i)[0]

    def _set(self, i: int, value: int) -> None:
        _U64.pack_into(self.buf, self.base + 8 * i, value)

    # ------------------------------------------------------------------ serve: the drive's runtime thread
    def hook(self, drive) -> None:
        """The cycle hook: the output values and the statusword of the cycle before into the next slot (the hook
        runs under the drive's lock: its object table is read directly)."""
        n = self._w
        o = drive.outputs
        off = self._slots + (n & _SLOT_MASK) * _SLOT_BYTES
        if o[13] is None:  # (the drive has published nothing yet)
            self._pack_slot(self.buf, off, n, *_NAN_SLOT_VALUES, n)
        else:
            self._pack_slot(self.buf, off, n, drive.objects[_STATUSWORD_KEY], o[1], o[3], o[9], o[5], o[6], o[7],
                            o[13], n)
        n += 1
        self._pack_u64(self.buf, self._w_end, n)
        self._w = n

    # ------------------------------------------------------------------ serve: the state thread
    def set_units(self, drive) -> None:
        """The conversion of the raw values to SI units as the drive has it now."""
        _F64X3.pack_into(self.buf, self.base + _UNITS_AT, float(drive.scaling.metres_per_unit),
                         float(drive.read_object(_RATED_TORQUE)) * 1e-3,
                         float(drive.read_object(_RATED_CURRENT)) * 1e-3)

    def set_state(self, message: bytes) -> None:
        """The axis' state message (JSON, at most :data:`STATE_BYTES`)."""
        if len(message) > STATE_BYTES:
            raise ValueError(f"state message of {len(message)} bytes (at most {STATE_BYTES})")
        s = self._word(_STATE_SEQ)
        self._set(_STATE_SEQ, s + 1)  # odd: being written
        self._set(_STATE_LEN, len(message))
        self.buf[self.base + _STATE_AT:self.base + _STATE_AT + len(message)] = message
        self._set(_STATE_SEQ, s + 2)

    def clients(self) -> int:
        return self._word(_CLIENTS)

    # ------------------------------------------------------------------ the server process
    def set_clients(self, n: int) -> None:
        self._set(_CLIENTS, n)

    def state(self) -> bytes:
        """The newest state message read whole (b"" before one was). While serve is writing one (its
        writer may hold the interpreter lock's turn for a while), the one before: this process never spins on
        the segment waiting for serve."""
        for _ in range(STATE_READ_TRIES):
            s1 = self._word(_STATE_SEQ)
            n = min(self._word(_STATE_LEN), STATE_BYTES)
            data = bytes(self.buf[self.base + _STATE_AT:self.base + _STATE_AT + n])
            if not s1 & 1 and s1 == self._word(_STATE_SEQ):
                self._last_state = data
                return data
        return self._last_state

    def units(self) -> tuple[float, float, float]:
        return _F64X3.unpack_from(self.buf, self.base + _UNITS_AT)

    def written(self) -> int:
        return self._word(_W_END)

    def slots(self, start: int, end: int) -> tuple[np.ndarray, int]:
        """Copies of the slots ``start`` .. ``end - 1`` and how many of the first were overwritten while copied."""
        view = np.frombuffer(self.buf, dtype=_SLOT_DTYPE, count=HANDOFF_SLOTS, offset=self._slots)
        seqs = np.arange(start, end)
        at = seqs & (HANDOFF_SLOTS - 1)
        block = np.empty(len(seqs), dtype=_SLOT_DTYPE)
        block["end"] = view["end"][at]  # (the ends first, the starts last: the reverse of the hook's order)
        block["sw"] = view["sw"][at]
        block["v"] = view["v"][at]
        block["seq"] = view["seq"][at]
        bad = np.flatnonzero((block["seq"] != seqs) | (block["end"] != seqs))
        return block, (int(bad[-1]) + 1 if len(bad) else 0)


class LongRing:
    """The server process' ring of one axis (module doc); ``seconds``: its length."""

    def __init__(self, block: PageBlock, cycle_s: float, seconds: float = 120.0):
        self.block = block
        self.cycle_s = float(cycle_s)
        self.capacity = max(1024, int(round(seconds / self.cycle_s)))
        self.taken = block.written()  # next slot seq to take (slots written before the server started are left)
        self.rows = np.full((self.capacity, len(COLUMNS)), np.nan)
        self.times_s = np.zeros(self.capacity)
        self.written = 0  # rows appended to the long ring (sequence number of the next row)
        self.lost = 0  # slots overwritten before the server process took them
        self._lost_until = 0  # rows before this sequence number may have gaps (a recording over them is refused)
        self._first_cycle: int | None = None
        self._carry = np.full(3, np.nan)  # velocity, torque, current of the last slot taken [SI]
        self._lock = threading.Lock()  # drain vs. slice

    def drain(self) -> tuple[int, int]:
        """Move what the hook wrote since the last call into the long ring; returns the range ``(first, end)``."""
        with self._lock:
            end = self.block.written()
            start = self.taken
            if end - start > HANDOFF_SLOTS - HANDOFF_MARGIN:  # the hook overwrote (or is about to) older slots
                skip = end - start - (HANDOFF_SLOTS - HANDOFF_MARGIN)
                self._lose(skip)
                start += skip
            if end <= start:
                return self.written, self.written
            slots, bad = self.block.slots(start, end)
            self.taken = end
            if bad:
                self._lose(bad)
                slots = slots[bad:]
            n_new = len(slots)
            if not n_new:
                return self.written, self.written
            raw = slots["v"]
            m_per_unit, rated_nm, rated_a = self.block.units()
            block = np.empty((n_new, len(COLUMNS)))
            block[:, :4] = raw[:, :4] * m_per_unit
            block[:, 4] = raw[:, 4] * (rated_nm * 1e-3)  # per mille of the rated torque
            block[:, 5] = raw[:, 5] * (rated_a * 1e-3)  # per mille of the rated current
            block[:, 6] = slots["sw"]
            # one instant per row: a slot holds 0x6064 / 0x60F4 as the position loop sampled them at the start of
            # its cycle, but velocity, torque and current at its end (the start of the next): row k takes those of
            # the slot before (the model's and `simulate`'s convention; the first row after a start or a loss
            # keeps its own)
            dyn = block[:, 3:6]
            prev = np.vstack((self._carry, dyn[:-1]))
            self._carry = dyn[-1].copy()
            block[:, 3:6] = np.where(np.isfinite(prev), prev, dyn)
            first = self.written
            if self._first_cycle is None:
                cyc = raw[0, 6]
                self._first_cycle = int(cyc) if np.isfinite(cyc) else 0
            seq = np.arange(first, first + n_new)
            times = (self._first_cycle + seq + self.lost) * self.cycle_s
            pos = seq % self.capacity
            self.rows[pos] = block
            self.times_s[pos] = times
            self.written = first + n_new
            return first, self.written

    def _lose(self, n: int) -> None:
        self.lost += n
        self._carry = np.full(3, np.nan)  # (the slot before the next one taken is gone)
        self._lost_until = self.written  # (the rows before it and after it are not contiguous)

    def oldest(self) -> int:
        """Sequence number of the oldest row still held."""
        return max(0, self.written - self.capacity, self._lost_until if self.lost else 0)

    def info(self) -> dict:
        """The ring part of a state message."""
        return {"written": self.written, "oldest": self.oldest(), "lost": self.lost,
                "capacity_s": self.capacity * self.cycle_s}

    def state_message(self) -> bytes:
        """The axis' newest state message from serve with this ring's figures added (b"" before the first)."""
        state = self.block.state()
        if not state.endswith(b"}"):
            return b""
        return state[:-1] + b', "ring": ' + json.dumps(self.info()).encode() + b"}"

    def slice(self, first: int, end: int) -> tuple[np.ndarray, np.ndarray]:
        """Rows ``first`` .. ``end - 1`` (times [s], rows); :class:`RecordingError` if they are not all held."""
        with self._lock:
            if not 0 <= first < end:
                raise RecordingError(f"from={first}, to={end}: need 0 <= from < to")
            if end > self.written:
                raise RecordingError(f"to={end}: only {self.written} samples recorded so far")
            oldest = self.oldest()
            if first < oldest:
                span = self.capacity * self.cycle_s
                raise RecordingError(f"from={first}: sample no longer held (oldest {oldest}; the ring keeps the last "
                                     f"{span:g} s" + (", and samples were lost before it)" if self.lost else ")"))
            pos = np.arange(first, end) % self.capacity
            return self.times_s[pos].copy(), self.rows[pos].copy()
