"""Every drive cycle's actual values for the live page: a cycle hook hands them over, the page's thread keeps them.

The drive's cycle hook (:meth:`SampleRing.hook`, runtime thread, under the drive's lock) only stores a reference
to the drive's published output tuple (:attr:`Drive.outputs <virtualaxis.drive.core.Drive.outputs>`, a new
tuple whenever a value changed) and the statusword in a preallocated hand-over list: no conversion, no
allocation of its own. The page's thread (:meth:`SampleRing.drain`, in the gap after a SYNC's PDOs) converts
what came since its last call to SI units in one NumPy step and appends it to a long ring of float64 rows
(``seconds`` of drive cycles): the scope streams from there and a recording is a slice of it, one row per
drive cycle. If the page's thread fell so far behind that the hand-over list wrapped, the rows it missed are
counted in :attr:`SampleRing.lost` and a recording spanning them is refused.

The hook runs at the start of a drive cycle: the values it stores are those published by the cycle before.
"""

from __future__ import annotations

import threading

import numpy as np

#: columns of a ring row (SI units; statusword as a number)
COLUMNS = ("pos_cmd", "pos_fb", "following_error", "vel_meas", "torque_meas", "current_q", "statusword")
#: position of each column's source value in Drive.outputs (0x6062, 0x6064, 0x60F4, 0x606C, 0x6077, 0x6078)
_OUT_INDEX = (1, 3, 9, 5, 6, 7)
_STATUSWORD_KEY = (0x6041, 0)
_RATED_CURRENT = 0x6075  # mA
_RATED_TORQUE = 0x6076  # mN m (N for a force actuator)
HANDOFF_SLOTS = 1 << 14  # drive cycles the page's thread may fall behind (16 s at a 1 ms cycle)
HANDOFF_MARGIN = 1 << 10  # slots kept clear of the hook's writing position while draining


class RecordingError(ValueError):
    """A requested slice of the ring is not (or no longer) held; the message says why."""


class SampleRing:
    """Per-cycle samples of one drive (see the module docstring); ``seconds``: length of the long ring."""

    def __init__(self, drive, seconds: float = 120.0):
        self.drive = drive
        self.cycle_s = float(drive.cycle_s)
        self.capacity = max(1024, int(round(seconds / self.cycle_s)))
        self._outs: list = [None] * HANDOFF_SLOTS  # Drive.outputs of each cycle
        self._sws: list = [None] * HANDOFF_SLOTS  # statusword of each cycle
        self._mask = HANDOFF_SLOTS - 1
        self.handed = 0  # cycles handed over by the hook (only the runtime thread writes it)
        self.rows = np.full((self.capacity, len(COLUMNS)), np.nan)
        self.times_s = np.zeros(self.capacity)
        self.written = 0  # rows appended to the long ring (sequence number of the next row)
        self.lost = 0  # hand-over slots overwritten before the page's thread took them
        self._lost_until = 0  # rows before this sequence number may have gaps (a recording over them is refused)
        self._first_cycle: int | None = None
        self._lock = threading.Lock()  # drain vs. slice

    # ------------------------------------------------------------------ runtime thread
    def hook(self, drive) -> None:
        """The cycle hook: keep the output tuple and the statusword of the cycle before (the hook runs under the
        drive's lock: its object table is read directly, ~0.4 us, not through read_object, ~4 us)."""
        n = self.handed
        i = n & self._mask
        self._outs[i] = drive.outputs
        self._sws[i] = drive.objects[_STATUSWORD_KEY]
        self.handed = n + 1

    def attach(self) -> SampleRing:
        self.drive.add_cycle_hook(self.hook)
        return self

    def detach(self) -> None:
        self.drive.remove_cycle_hook(self.hook)

    # ------------------------------------------------------------------ page thread
    def drain(self) -> tuple[int, int]:
        """Move what the hook handed over into the long ring; returns the sequence range ``(first, end)`` added."""
        with self._lock:
            end = self.handed
            start = self.written + self.lost
            if end - start > HANDOFF_SLOTS - HANDOFF_MARGIN:  # the hook overwrote (or is about to) older slots
                skip = end - start - (HANDOFF_SLOTS - HANDOFF_MARGIN)
                self.lost += skip
                start += skip
                self._lost_until = self.written  # (the rows before it and after it are not contiguous)
            if end <= start:
                return self.written, self.written
            a, b = start & self._mask, end & self._mask
            if a < b:
                out_refs, sws = self._outs[a:b], self._sws[a:b]
                self._outs[a:b] = self._sws[a:b] = [None] * (b - a)  # (no tuple kept alive longer than needed)
            else:
                out_refs, sws = self._outs[a:] + self._outs[:b], self._sws[a:] + self._sws[:b]
                self._outs[a:] = self._sws[a:] = [None] * (HANDOFF_SLOTS - a)
                self._outs[:b] = self._sws[:b] = [None] * b
            n_new = len(out_refs)
            outs = np.array(out_refs, dtype=float)
            if outs.ndim != 2:  # (the drive had published nothing yet: a tuple of None)
                outs = np.full((n_new, 15), np.nan)
            drive = self.drive
            m_per_unit = float(drive.scaling.metres_per_unit)
            rated_nm = float(drive.read_object(_RATED_TORQUE)) * 1e-3
            rated_a = float(drive.read_object(_RATED_CURRENT)) * 1e-3
            block = np.empty((n_new, len(COLUMNS)))
            block[:, :4] = outs[:, _OUT_INDEX[:4]] * m_per_unit
            block[:, 4] = outs[:, _OUT_INDEX[4]] * (rated_nm * 1e-3)  # per mille of the rated torque
            block[:, 5] = outs[:, _OUT_INDEX[5]] * (rated_a * 1e-3)  # per mille of the rated current
            block[:, 6] = sws
            first = self.written
            if self._first_cycle is None:
                cyc = outs[0, 13]
                self._first_cycle = int(cyc) if np.isfinite(cyc) else 0
            seq = np.arange(first, first + n_new)
            times = (self._first_cycle + seq + self.lost) * self.cycle_s
            pos = seq % self.capacity
            self.rows[pos] = block
            self.times_s[pos] = times
            self.written = first + n_new
            return first, self.written

    def oldest(self) -> int:
        """Sequence number of the oldest row still held."""
        return max(0, self.written - self.capacity, self._lost_until if self.lost else 0)

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
