"""SYNC consumer: COB-ID 0x1005, communication cycle period 0x1006 (SYNC timeout = 1.5 periods -> EMCY
0x8100), synchronous window 0x1007 and the SYNC counter (0x1019).

SYNC monitoring (CiA 301 7.2.5: the consumer reacts when no SYNC arrives within 1.5 communication cycle
periods) is judged on the frames' own **arrival times** (the bus receive timestamp, mapped onto the caller's
clock), never on when the drive thread got round to handling them:

- a SYNC whose arrival is more than 1.5 x 0x1006 after the previous one's is a timeout (detected when it is
  handled, if the timer below did not catch it first);
- between SYNCs, a poll declares the timeout when the time since the last arrival exceeds 1.5 x 0x1006 plus
  the receive path's delivery delay (``delivery_allowance_s``: 3 x the largest recent delay between a SYNC's
  arrival and its hand-over to the stack, at least 1 ms) and only while the bus's receive socket holds no
  unread frame, so that a SYNC still in the receive path of a busy
  machine is not mistaken for a missing one.

Each gap longer than 1.5 periods gives exactly one EMCY 0x8100; a gap shorter never gives one.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from virtualaxis.canopen_slave import errors as ab
from virtualaxis.canopen_slave.errors import SdoAbort

if TYPE_CHECKING:
    from virtualaxis.canopen_slave.context import CommErrorNode

SYNC_GENERATE = 0x40000000
SYNC_EXTENDED = 0x20000000
MIN_ALLOWANCE_S = 1e-3
MAX_ALLOWANCE_S = 0.1


class SyncConsumer:
    def __init__(self, slave: CommErrorNode):
        self.slave = slave
        #: largest 0x1006 accepted [us] (None: any); a lockstep runtime sets it (drive time per SYNC is bounded)
        self.max_period_us: int | None = None
        self.configure()
        self.last_sync_s: float | None = None     # arrival of the last SYNC [s, caller's clock]
        self.delivery_delay_s = 0.0                  # decaying max of (hand-over - arrival) of SYNC frames [s]

    def configure(self) -> None:
        od = self.slave.od
        self.cob_id = od.value(0x1005) & 0x7FF
        self.window_s = od.value(0x1007) * 1e-6
        self.timeout_s = 1.5 * od.value(0x1006) * 1e-6      # 0 = no SYNC monitoring
        self.timed_out = False
        if self.timeout_s == 0.0:
            self.slave.clear_comm_error(0x8100)  # monitoring off: a SYNC timeout reported is moot
        overflow = od.value(0x1019) if (0x1019, 0) in od else 0
        self.counter_enabled = overflow >= 2
        self.expected_dlc = 1 if self.counter_enabled else 0

    def validate_write(self, index: int, _sub: int, value: int) -> None:
        if index == 0x1006 and self.max_period_us is not None and value > self.max_period_us:
            raise SdoAbort(ab.VALUE_TOO_HIGH, f"communication cycle period {value} us exceeds the "
                                              f"{self.max_period_us} us this node serves in SYNC lockstep")
        if index == 0x1005 and value & (SYNC_GENERATE | SYNC_EXTENDED):
            raise SdoAbort(ab.INVALID_VALUE, "this device is a SYNC consumer with an 11-bit COB-ID only")
        if index == 0x1019:
            if value == 1 or value > 240:
                raise SdoAbort(ab.INVALID_VALUE, "SYNC counter overflow must be 0 or 2..240")
            if self.slave.od.value(0x1006) != 0:
                raise SdoAbort(ab.DEVICE_STATE, "0x1019 can only change while 0x1006 is 0")

    def after_write(self, _index: int, _sub: int) -> None:
        self.configure()
        self.slave.rebuild_dispatch()

    def check_frame(self, data: bytes) -> int | None:
        """SYNC counter of a valid SYNC frame (0 without counter), None for a wrong length."""
        if len(data) != self.expected_dlc:
            return None
        return data[0] if self.counter_enabled else 0

    @property
    def delivery_allowance_s(self) -> float:
        """Receive-path delay allowed for before a missing SYNC is declared by the timer [s]."""
        return min(MAX_ALLOWANCE_S, max(MIN_ALLOWANCE_S, 3.0 * self.delivery_delay_s))

    def note_delivery(self, delay_s: float) -> None:
        """One SYNC's delay between its arrival on the bus and its hand-over to the stack [s]."""
        decayed = self.delivery_delay_s * 0.995
        self.delivery_delay_s = delay_s if delay_s > decayed else decayed

    def on_arrival(self, arrival_s: float) -> bool:
        """A valid SYNC arrived at ``arrival_s``; True if the gap since the previous one was a timeout that
        the timer had not reported yet."""
        last = self.last_sync_s
        late = (self.timeout_s > 0.0 and last is not None and not self.timed_out
                and arrival_s - last > self.timeout_s)
        if last is None or arrival_s > last:
            self.last_sync_s = arrival_s
        self.timed_out = False
        return late

    def check_timeout(self, now_s: float, rx_pending=None) -> bool:
        """True once when SYNCs stop for 1.5 x 0x1006 (monitoring starts with the first SYNC);
        ``rx_pending()`` (optional) says whether frames still wait in the receive socket: then not yet."""
        timeout_s, last = self.timeout_s, self.last_sync_s
        if timeout_s <= 0.0 or last is None or self.timed_out:
            return False
        gap_s = now_s - last
        # (the allowance is at least MIN_ALLOWANCE_S: a gap within that needs no allowance computed)
        if gap_s > timeout_s + MIN_ALLOWANCE_S and gap_s > timeout_s + self.delivery_allowance_s:
            if rx_pending is not None and rx_pending():
                return False
            self.timed_out = True
            return True
        return False

    def window_open(self, now_s: float) -> bool:
        """True while synchronous PDOs may still be sent for the last SYNC (0x1007 = 0: always)."""
        return self.window_s <= 0.0 or self.last_sync_s is None or now_s - self.last_sync_s <= self.window_s
