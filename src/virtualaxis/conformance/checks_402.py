"""CiA 402 checks (drive profile): state machine, modes of operation, faults, and the field behaviours
of a machine-tool drive under faults and loss of control.

Positions, velocities and accelerations are in the node's own units (0x6064 / 0x606C / 0x6085); distances
are chosen in mm through ``ctx.units_per_mm`` (``--units-per-mm``, default 1000 = 1 um per unit). The master
maps, as the standard allows (CiA 301 dynamic mapping): TPDO1 = statusword + position actual value, TPDO2 =
velocity actual value (both on every SYNC), RPDO1 = controlword + target position (asynchronous), and runs
SYNC every ``ctx.sync_period_s`` while the axis moves (a drive locked to SYNC advances only on SYNC).
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass

import canopen

from virtualaxis.conformance.runner import Context, Fail, RunError, Skip, boot, check

STATE_MASK = 0x6F
SOD, RTSO, SO, OE, QSA = 0x40, 0x21, 0x23, 0x27, 0x07
#: real time: a stream that sent fewer than this share of the periods' set-points was not sent in time by the
#: master or the host (an error of the run, not a verdict on the node)
STREAM_MIN_SENT = 0.8
#: real time: longest wait [s] for the SYNC answers of the sending before a stream to pass (3 quiet periods)
STREAM_SETTLE_S = 0.05
MODES = {1: "PP", 3: "PV", 4: "PT", 6: "HM", 8: "CSP", 9: "CSV", 10: "CST"}
MODE_BITS = {1: 0x1, 3: 0x4, 4: 0x8, 6: 0x20, 7: 0x40, 8: 0x80, 9: 0x100, 10: 0x200}


def _is_fault(sw: int) -> bool:
    return sw & 0x4F == 0x08 or sw & 0x4F == 0x0F


@dataclass
class Sample:
    t: float
    sw: int
    pos: int
    vel: int | None = None


class Motion:
    """Process-data set-up of the motion checks and the samples of TPDO1/TPDO2."""

    def __init__(self, ctx: Context):
        self.ctx = ctx
        n = ctx.node_id
        self.tpdo1, self.tpdo2, self.rpdo1 = 0x180 + n, 0x280 + n, 0x200 + n
        boot(ctx)
        try:
            self.map(0x1800, 0x1A00, self.tpdo1, [0x60410010, 0x60640020], 1)
            self.map(0x1801, 0x1A01, self.tpdo2, [0x606C0020], 1)
            self.map(0x1400, 0x1600, self.rpdo1, [0x60400010, 0x607A0020], 255)
        except canopen.SdoAbortedError as exc:
            raise Skip(f"dynamic PDO mapping refused (abort 0x{exc.code:08X}): the motion checks need "
                       "TPDO1 = 0x6041 + 0x6064, TPDO2 = 0x606C, RPDO1 = 0x6040 + 0x607A") from None
        ctx.write(0x1017, 0, 50)
        ctx.nmt(0x01)
        time.sleep(0.03)
        self._stream: threading.Thread | None = None
        self._stop = threading.Event()
        self.target = 0
        self.cw = 0x0F
        self.step_units = 0.0
        self.streamed = 0  # SYNCs the stream has sent
        self.sent: list[float] = []  # the targets of the stream under way, one per SYNC, in order
        self._stream_mark = 0  # the frame log's length when the stream under way began

    def map(self, comm: int, mapping: int, cob: int, entries: list[int], ttype: int) -> None:
        ctx = self.ctx
        ctx.write(comm, 1, cob | 0x80000000)
        ctx.write(mapping, 0, 0)
        for i, e in enumerate(entries, 1):
            ctx.write(mapping, i, e)
        ctx.write(mapping, 0, len(entries))
        ctx.write(comm, 2, ttype)
        ctx.write(comm, 1, cob)

    def samples(self, mark: int) -> list[Sample]:
        out: list[Sample] = []
        vel = None
        for t, cob, d in self.ctx.frames.since(mark):
            if cob == self.tpdo2 and len(d) >= 4:
                vel = int.from_bytes(d[0:4], "little", signed=True)
                if out:
                    out[-1].vel = vel
            elif cob == self.tpdo1 and len(d) >= 6:
                out.append(Sample(t, int.from_bytes(d[0:2], "little"), int.from_bytes(d[2:6], "little", signed=True),
                                  vel))
        return out

    def last(self, timeout: float = 0.5) -> Sample:
        """The latest TPDO1 sample after two new ones (``timeout``: node time, see ``Context.deadline``)."""
        mark = self.ctx.frames.mark()
        expired = self.ctx.deadline(timeout)
        while True:
            s = self.samples(mark)
            if len(s) >= 2:
                return s[-1]
            if expired():
                raise Fail(f"no TPDO1 (statusword + position) on SYNC within {timeout:g} s")
            time.sleep(0.005)

    def at_rest_velocity(self, n: int = 20, timeout: float = 1.0) -> tuple[Sample, float]:
        """The last TPDO1 sample and the mean velocity (units/s) over the last ``n`` SYNC periods, from the
        positions of ``n`` + 1 consecutive TPDO1 samples (one per SYNC). "At rest" is judged on this mean, not on
        one 0x606C sample: a velocity from encoder differences reads +-1 increment per cycle at standstill
        (1 mm/s at 1 um and 1 ms), and under load the plant time between two wall-clock samples is not the SYNC
        period (lockstep: time advances per SYNC)."""
        mark = self.ctx.frames.mark()
        expired = self.ctx.deadline(timeout)
        while True:
            s = self.samples(mark)
            if len(s) >= n + 1:
                break
            if expired():
                raise Fail(f"{len(s)} TPDO1 in {timeout:g} s, {n + 1} needed to judge standstill")
            time.sleep(0.005)
        window = s[-(n + 1):]
        return s[-1], (window[-1].pos - window[0].pos) / (n * self.ctx.sync_period_s)

    def rpdo(self, cw: int, target: int) -> None:
        data = cw.to_bytes(2, "little") + int(target).to_bytes(4, "little", signed=True)
        self.ctx.net.send_message(self.rpdo1, data)

    def stream(self, start: int, velocity_units_s: float) -> None:
        """CSP: every SYNC period, RPDO1 (CW 0x0F + target advanced by v * period), then SYNC."""
        ctx = self.ctx
        ctx.stop_sync()
        self.stop_stream()  # (one stream at a time)
        self.target = float(start)
        self.step_units = velocity_units_s * ctx.sync_period_s
        self._stop.clear()
        ctx.streams += 1
        self.sent = []
        if not ctx.lockstep:  # answers to the SYNCs sent before this stream still on their way: let them pass
            end = time.monotonic() + STREAM_SETTLE_S
            while time.monotonic() < end and ctx.frames.wait(ctx.frames.mark(), self.tpdo1, None,
                                                            3 * ctx.sync_period_s) is not None:
                pass
        self._stream_mark = ctx.frames.mark()

        def run() -> None:
            period = ctx.sync_period_s
            nxt = time.monotonic()
            first = True
            while not self._stop.is_set():
                self.target += self.step_units
                self.rpdo(self.cw, round(self.target))
                self.sent.append(self.target)
                ctx.sync_once(answer_cob=self.tpdo1)  # (lockstep: waits for the node's answer)
                ctx.periodic_sent(restart=first)
                first = False
                self.streamed += 1
                nxt += period
                delay = nxt - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                else:
                    nxt = time.monotonic()

        self._stream = threading.Thread(target=run, daemon=True, name="conformance-csp")
        self._stream.start()

    def tracking(self) -> list[tuple[float, Sample]]:
        """The stream's targets paired with the node's TPDO1 samples in order: the k-th sample since the stream
        began answers its k-th SYNC, sent after its k-th target (a sample is judged against the target of its
        own SYNC, not against the target the stream has reached when the master looks)."""
        return list(zip(list(self.sent), self.samples(self._stream_mark), strict=False))

    def run_syncs(self, n: int, timeout_s: float | None = None) -> None:
        """Let the stream run for ``n`` SYNC periods of the node: ``n`` SYNCs (lockstep: the node's time is
        the SYNC count), ``n`` periods of wall time (real time; fewer than :data:`STREAM_MIN_SENT` x ``n``
        set-points sent meanwhile is an error of the run: the master or the host missed the stimulus)."""
        if not self.ctx.lockstep:
            s0 = self.streamed
            time.sleep(n * self.ctx.sync_period_s)
            sent = self.streamed - s0
            # the sending thread may wait up to two of the interpreter's thread switch intervals for the GIL: a
            # window that short says nothing about the master
            slack = 2.0 * sys.getswitchinterval() / self.ctx.sync_period_s
            if self._stream is not None and sent < STREAM_MIN_SENT * n - slack:
                raise RunError(f"the master sent {sent} set-points + SYNCs in {n} periods of "
                               f"{self.ctx.sync_period_s * 1e3:g} ms: the master or the host missed the stimulus")
            return
        goal = self.streamed + n
        timeout_s = timeout_s if timeout_s is not None else max(10.0, 0.1 * n)
        end = time.monotonic() + timeout_s
        while self.streamed < goal:
            if time.monotonic() > end:
                raise RunError(f"{goal - self.streamed} of {n} SYNCs not sent in {timeout_s:g} s: the master or "
                               "the host is too slow")
            time.sleep(0.002)

    def pause(self, seconds: float) -> None:
        """Let ``seconds`` of the node's time pass while the stream runs (lockstep: that many SYNCs)."""
        self.run_syncs(max(1, round(seconds / self.ctx.sync_period_s)))

    def stop_stream(self) -> None:
        self._stop.set()
        if self._stream is not None:
            self._stream.join(2.0)
            self._stream = None
            self.ctx.streams -= 1

    def wait(self, pred, timeout: float, what: str) -> Sample:
        expired = self.ctx.deadline(timeout)  # (lockstep: node time, in SYNCs)
        while True:
            s = self.last()
            if pred(s):
                return s
            if expired():
                raise Fail(f"{what} not reached in {timeout:g} s (SW 0x{s.sw:04X}, position {s.pos})")
            time.sleep(0.01)

    def close(self) -> None:
        self.stop_stream()
        self.ctx.stop_sync()


def _start_pp(ctx: Context, mo: Motion, velocity_mm_s: float) -> float:
    """Profile position enabled under SYNC with 0x6081 = ``velocity_mm_s``, 0x6083/0x6084 = 2 m/s^2; the actual
    position (units) to move from."""
    ctx.write(0x6081, 0, ctx.mm(velocity_mm_s))
    ctx.write(0x6083, 0, ctx.mm(2000))
    ctx.write(0x6084, 0, ctx.mm(2000))
    _enable_mode(ctx, 1)
    ctx.start_sync()
    return mo.last().pos


def _enable_mode(ctx: Context, mode: int) -> None:
    supported = ctx.read(0x6502)
    if not supported & MODE_BITS.get(mode, 0):
        raise Skip(f"mode {mode} ({MODES.get(mode, '?')}) not supported (0x6502 = 0x{supported:X})")
    ctx.write(0x6060, 0, mode)
    expired = ctx.deadline(0.5)
    while ctx.poll(0x6061) != mode:
        if expired():
            raise Fail(f"0x6061 did not follow 0x6060 = {mode} within 0.5 s")
        time.sleep(0.005)
    ctx.enable()


# ============================================================================ state machine
@check("402-SM-1", "sm", "CiA 402 6.1.3 (power drive state machine, transitions 2, 3, 4; statusword bit 9 "
       "remote); CL 12",
       "after reset: CW 0x0F and 0x07 in switch on disabled (no transition leads there), then CW 0x06, 0x07, 0x0F "
       "by SDO", "switch on disabled stays (SW & 0x4F = 0x40); then SW & 0x6F = 0x21, 0x23, 0x27, each with bit 9 "
       "(remote: the controlword is obeyed); real time: whole chain well inside 0.8 s")
def sm_enable(ctx: Context) -> str:
    boot(ctx)
    sw = ctx.sw()
    if sw & 0x4F != 0x40:
        raise Fail(f"SW 0x{sw:04X} after boot, expected switch on disabled")
    for cw in (0x0F, 0x07):  # enable operation / switch on: commands without a transition from here
        ctx.write(0x6040, 0, cw)
        expired = ctx.deadline(0.1)
        while not expired():
            sw = ctx.poll(0x6041)
            if sw & 0x4F != 0x40:
                raise Fail(f"CW 0x{cw:02X} in switch on disabled gave SW 0x{sw:04X}: only shutdown (0x06) leaves "
                           "switch on disabled (transition 2)")
            time.sleep(0.01)
    t0 = time.monotonic()
    for cw, exp in ((0x06, RTSO), (0x07, SO), (0x0F, OE)):
        ctx.write(0x6040, 0, cw)
        sw = ctx.wait_sw(STATE_MASK, exp, 0.5, f"CW 0x{cw:02X}")
        if not sw & 0x200:
            raise Fail(f"SW 0x{sw:04X} after CW 0x{cw:02X}: bit 9 (remote) is 0 although the drive obeys the "
                       "controlword")
    dt = time.monotonic() - t0
    ctx.disable()
    if ctx.lockstep:  # the node changes state on the SDO write itself: wait_sw judged it in reads of the node
        return f"0x21 -> 0x23 -> 0x27, each seen in the reads after its write ({dt * 1e3:.0f} ms of wall time)"
    if dt > 0.8:
        raise Fail(f"chain took {dt:.2f} s")
    return f"0x21 -> 0x23 -> 0x27 in {dt * 1e3:.0f} ms"


@check("402-SM-2", "sm", "CiA 402 6.1.3 (transitions 5, 6, 7, 8, 9, 4); CL 13",
       "in operation enabled: CW 0x07, 0x0F, 0x06, then 0x07, 0x0F, 0x00",
       "switched on 0x23, enabled 0x27, ready 0x21, ..., switch on disabled (SW & 0x4F = 0x40)")
def sm_back(ctx: Context) -> str:
    boot(ctx)
    ctx.start_sync()  # stop reactions (0x605C, 0x605B) ramp over drive cycles: a SYNC-locked drive needs SYNC
    ctx.enable()
    seq = ((0x07, STATE_MASK, SO), (0x0F, STATE_MASK, OE), (0x06, STATE_MASK, RTSO), (0x07, STATE_MASK, SO),
           (0x0F, STATE_MASK, OE), (0x00, 0x4F, 0x40))
    for cw, mask, exp in seq:
        ctx.write(0x6040, 0, cw)
        ctx.wait_sw(mask, exp, 1.0, f"CW 0x{cw:02X}")
    return "all transitions as specified"


@check("402-SM-3", "sm", "CiA 402 6.1.3 (quick stop, transitions 11, 12, 16); 0x605A; CL 13, 14, 17",
       "0x605A = 6, CW 0x02; CW 0x0F; 0x605A = 2, CW 0x02",
       "quick stop active (SW & 0x6F = 0x07, bit 5 = 0), back to 0x27 with 0x0F; with 2: switch on disabled")
def sm_quick_stop(ctx: Context) -> str:
    boot(ctx)
    try:
        ctx.write(0x605A, 0, 6)
    except canopen.SdoAbortedError as exc:
        raise Skip(f"0x605A = 6 refused (0x{exc.code:08X})") from None
    ctx.start_sync()
    ctx.enable()
    ctx.write(0x6040, 0, 0x02)
    sw = ctx.wait_sw(STATE_MASK, QSA, 1.0, "quick stop (0x605A = 6)")
    if sw & 0x20:
        raise Fail(f"SW 0x{sw:04X}: bit 5 set in quick stop active")
    ctx.write(0x6040, 0, 0x0F)
    ctx.wait_sw(STATE_MASK, OE, 1.0, "CW 0x0F from quick stop active")
    ctx.write(0x605A, 0, 2)
    ctx.write(0x6040, 0, 0x02)
    ctx.wait_sw(0x4F, 0x40, 1.5, "quick stop with 0x605A = 2 ends in switch on disabled")
    return "0x07 (bit 5 = 0) -> 0x27; with 0x605A = 2 -> 0x40"


# ============================================================================ modes
#: MODE-1: the velocity target every mode is given [mm/s]; the modes that must follow it (the others hold)
MODE_PROBE_MM_S = 10.0
MODE_PROBE_S = 0.1
VELOCITY_MODES = (3, 9)
#: MODE-1: the modes run under the probe (PT and HM have no target the probe can judge)
PROBED_MODES = (1, 3, 8, 9, 10)


@check("402-MODE-1", "modes", "CiA 402 6.2 (0x6060 / 0x6061; the drive runs the mode 0x6061 displays); CL 18",
       "0x6060 = every mode set in 0x6502; then each of PP, PV, CSP, CSV, CST (those supported) enabled under SYNC "
       "with 0x607A = actual position, 0x60FF = 10 mm/s (toward the middle of the travel), 0x6071 = 0, for 0.2 s "
       "of node time",
       "0x6061 = the mode within 0.5 s; the drive runs it: in PV / CSV it follows 0x60FF (travel >= half of "
       "v t), in PP / CSP / CST it holds its position (travel < a quarter of v t)")
def modes_follow(ctx: Context) -> str:
    boot(ctx)
    supported = ctx.read(0x6502)
    seen = []
    for m, bit in MODE_BITS.items():
        if supported & bit:
            ctx.write(0x6060, 0, m)
            expired = ctx.deadline(0.5)
            while (got := ctx.poll(0x6061)) != m:
                if expired():
                    raise Fail(f"0x6061 = {got} 0.5 s after 0x6060 = {m}")
                time.sleep(0.005)
            seen.append(m)
    mo = Motion(ctx)  # (TPDO1 answers every SYNC: the travel is judged over a count of the node's cycles)
    try:
        ran = [_runs_the_mode(ctx, mo, m) for m in PROBED_MODES if supported & MODE_BITS[m]]
    finally:
        mo.close()
        ctx.disable()
    return f"modes {seen} displayed in 0x6061; travel in {MODE_PROBE_S:g} s [units]: " + ", ".join(ran)


def _runs_the_mode(ctx: Context, mo: Motion, mode: int) -> str:
    """``mode`` enabled with targets of every mode at once (0x607A = actual position, 0x60FF = the probe
    velocity, 0x6071 = 0); the travel over :data:`MODE_PROBE_S` of node time (TPDO1 positions that many SYNC
    periods apart) tells which target the drive follows."""
    name = MODES[mode]
    v = _toward_middle(ctx) * ctx.mm(MODE_PROBE_MM_S)
    n = round(MODE_PROBE_S / ctx.sync_period_s)
    ctx.write(0x6083, 0, ctx.mm(2000))
    ctx.write(0x6084, 0, ctx.mm(2000))
    if 0x6071 in ctx.od:
        ctx.write(0x6071, 0, 0)
    _enable_mode(ctx, mode)
    ctx.start_sync()
    try:  # the targets once enabled (a cyclic mode takes its target in the cycle after it is written)
        ctx.write(0x607A, 0, mo.last().pos)
        ctx.write(0x60FF, 0, v)
        ctx.sleep(0.02)  # (the velocity modes' acceleration)
        _, v_mean = mo.at_rest_velocity(n, timeout=max(2 * MODE_PROBE_S, 5.0))  # (collects; judges nothing)
    finally:
        ctx.write(0x60FF, 0, 0)
        ctx.sleep(0.05)  # (to rest before the next mode)
        ctx.stop_sync()
        ctx.disable()
    travel = round(v_mean * MODE_PROBE_S * (1 if v > 0 else -1))
    expected = abs(v) * MODE_PROBE_S
    ctx.note(f"{name}: {travel:+d} units toward 0x60FF = {v} in {n} SYNC periods")
    if mode in VELOCITY_MODES and travel < 0.5 * expected:
        raise Fail(f"0x6061 = {mode} ({name}) but the drive does not follow 0x60FF = {v}: travelled {travel} units in "
                   f"{MODE_PROBE_S:g} s, expected about {expected:.0f} (does it run another mode?)")
    if mode not in VELOCITY_MODES and abs(travel) >= 0.25 * expected:
        raise Fail(f"0x6061 = {mode} ({name}) but the drive follows the velocity target 0x60FF = {v}: travelled "
                   f"{travel} units in {MODE_PROBE_S:g} s with 0x607A = its position and 0x6071 = 0 (does it run "
                   "another mode?)")
    return f"{name} {travel:+d}"


@check("402-PP-1", "modes", "CiA 402 12 (profile position: set-point handshake, target reached); CL 19",
       "PP, 0x6081 = 100 mm/s, 0x607A = actual +/- 10 mm (toward the middle of the travel), CW 0x1F then 0x0F",
       "bit 12 = 1 (acknowledge), bit 12 = 0 after bit 4 drops, bit 10 = 1 inside 0x6067 at the target")
def pp_move(ctx: Context) -> str:
    mo = Motion(ctx)
    try:
        p0 = _start_pp(ctx, mo, velocity_mm_s=100)
        target = p0 + _toward_middle(ctx) * ctx.mm(10)
        ctx.write(0x607A, 0, target)
        ctx.write(0x6040, 0, 0x1F)
        ctx.wait_sw(0x1000, 0x1000, 0.5, "set-point acknowledge (bit 12)")
        ctx.write(0x6040, 0, 0x0F)
        ctx.wait_sw(0x1000, 0x0000, 0.5, "bit 12 cleared after CW bit 4 = 0")
        s = mo.wait(lambda s: s.sw & 0x400 and abs(s.pos - target) < ctx.mm(1), 3.0, "target reached")
        window = ctx.read(0x6067)
        if abs(s.pos - target) > window:
            raise Fail(f"target reached at {s.pos}, target {target}, window {window}")
        return f"moved {p0} -> {s.pos} (target {target}), handshake as specified"
    finally:
        mo.close()
        ctx.disable()


@check("402-PV-1", "modes", "CiA 402 11 (profile velocity: velocity reached, speed zero); CL 20",
       "PV, 0x60FF = +/-50 mm/s (toward the middle of the travel), then 0",
       "bit 10 (velocity reached) at 50 mm/s; bit 12 (speed zero) at 0")
def pv_move(ctx: Context) -> str:
    mo = Motion(ctx)
    try:
        ctx.write(0x6083, 0, ctx.mm(2000))
        ctx.write(0x6084, 0, ctx.mm(2000))
        _enable_mode(ctx, 3)
        ctx.start_sync()
        v_target = _toward_middle(ctx) * ctx.mm(50)
        ctx.write(0x60FF, 0, v_target)
        # bit 10 of the statusword sampled before the drive's next cycle still answers the old target (0, reached
        # at rest): the axis moving (bit 12, speed zero, cleared) shows the new target has been taken
        ctx.wait_sw(0x1000, 0, 1.5, "speed no longer zero (bit 12) after the new target")
        ctx.wait_sw(0x400, 0x400, 1.5, "velocity reached (bit 10)")
        v = ctx.read(0x606C)
        if abs(v - v_target) > ctx.mm(5):
            raise Fail(f"0x606C = {v} with bit 10 set, target {v_target}")
        ctx.write(0x60FF, 0, 0)
        ctx.wait_sw(0x1000, 0x1000, 1.5, "speed zero (bit 12)")
        return f"0x606C = {v} at bit 10; bit 12 at rest"
    finally:
        mo.close()
        ctx.disable()


@check("402-CSP-1", "modes", "CiA 402 (cyclic synchronous position); CL 22",
       "CSP, RPDO1 target advanced +/-50 mm/s (toward the middle of the travel) every SYNC for 0.4 s",
       "the axis follows: bit 12 = 1, "
       "|position - target| < 1 mm while moving (median after the first 0.1 s) and < 0x6067 after the stream "
       "stops")
def csp_follow(ctx: Context) -> str:
    mo = Motion(ctx)
    try:
        _enable_mode(ctx, 8)
        p0 = ctx.read(0x6064)
        d = _toward_middle(ctx)
        mo.stream(p0, d * ctx.mm(50))
        mo.run_syncs(400)
        pairs = mo.tracking()
        if not pairs:
            raise Fail("no TPDO1 (statusword + position) answered the stream's SYNCs")
        # the lag while moving at speed: the median over the stream's last three quarters (past the first 0.1 s,
        # where the lag builds up), so that one late answer of a busy host (its position from before a stall)
        # does not stand for the drive's tracking
        steady = sorted(abs(t - s.pos) for t, s in pairs[len(pairs) // 4:])
        err = steady[len(steady) // 2]
        mo.step_units = 0.0
        mo.run_syncs(300)
        s2 = mo.last()
        final = abs(round(mo.target) - s2.pos)
        if not s2.sw & 0x1000:
            raise Fail(f"SW 0x{s2.sw:04X}: bit 12 (drive follows the target) not set in CSP")
        if d * (s2.pos - p0) < ctx.mm(10):
            raise Fail(f"moved {s2.pos - p0} units for a 20 mm stream")
        if err > ctx.mm(1):
            raise Fail(f"{err:.0f} units behind the target while moving at 50 mm/s (median; expected < 1 mm)")
        if final > max(ctx.read(0x6067), ctx.mm(0.05)):
            raise Fail(f"settled {final} units from the target")
        return f"lag {err:.0f} units while moving, {final} units after; bit 12 set"
    finally:
        mo.close()
        ctx.disable()


@check("402-HM-1", "modes", "CiA 402 10 (homing, methods 35 / 37 on the current position); CL 21",
       "HM, 0x6098 = 37 (or 35), 0x607C = 1 mm, CW 0x1F", "bits 12 and 10 set (homing attained), 0x6064 = 0x607C")
def homing_current_position(ctx: Context) -> str:
    boot(ctx)
    supported = ctx.read(0x6502)
    if not supported & MODE_BITS[6]:
        raise Skip(f"homing mode not supported (0x6502 = 0x{supported:X})")
    held = ctx.read(0x6098) if 0x6098 in ctx.od else None
    if held in (35, 37):  # the method the node holds is one it offers: writing it back is no value error
        try:
            ctx.write(0x6098, 0, held)
        except canopen.SdoAbortedError as exc:
            if exc.code in (0x06090030, 0x06090031, 0x06090032, 0x06090036):
                raise Fail(f"0x6098 holds homing method {held} but writing it back is refused as a value "
                           f"(0x{exc.code:08X})") from None
    mo = Motion(ctx)
    try:
        for method in (37, 35):
            try:
                ctx.write(0x6098, 0, method)
                break
            except canopen.SdoAbortedError:
                continue
        else:
            raise Skip("homing methods 37 and 35 both refused")
        ctx.write(0x607C, 0, ctx.mm(1))
        _enable_mode(ctx, 6)
        ctx.start_sync()
        ctx.write(0x6040, 0, 0x1F)
        # judged on TPDO1 (statusword and position of the same cycle) from the second SYNC answer after the
        # write: the first carries the values from before the cycle that starts the homing, and a node homed
        # earlier shows bits 12 / 10 before it homes again
        after = ctx.frames.mark()
        expired = ctx.deadline(2.0)
        while True:
            samples = mo.samples(after)[1:]
            first = next((s for s in samples if s.sw & 0x3400 == 0x1400), None)
            if first is not None:
                break
            if expired():
                sw = samples[-1].sw if samples else ctx.poll(0x6041)
                raise Fail(f"homing attained (bits 13/12/10 = 0/1/1): SW 0x{sw:04X} after 2 s")
            time.sleep(0.005)
        ctx.note(f"TPDO1 at homing attained: SW 0x{first.sw:04X}, 0x6064 = {first.pos}")
        if abs(first.pos - ctx.mm(1)) > ctx.mm(0.01):
            raise Fail(f"0x6064 = {first.pos} when homing on the current position was attained, expected 0x607C = "
                       f"{ctx.mm(1)}")
        return f"method {method}: 0x6064 = {first.pos} at homing attained"
    finally:
        mo.close()
        ctx.disable()


@check("402-FE-1", "modes", "CiA 402 (following error 0x6065 / 0x6066, EMCY 0x8611); CiA 301 EMCY; CL 15, 24",
       "PP move at 100 mm/s with 0x6065 = 1 unit", "fault reaction -> fault (SW & 0x4F = 0x08), EMCY 0x8611 with "
       "error register bit 0, 0x1001 bit 0 in fault, "
       "0x603F = 0x8611, 0x1003:1 = 0x8611; CW 0x80 edge -> switch on disabled and EMCY 0x0000")
def following_error_fault(ctx: Context) -> str:
    mo = Motion(ctx)
    try:
        ctx.write(0x6081, 0, ctx.mm(100))
        ctx.write(0x6083, 0, ctx.mm(2000))
        ctx.write(0x6084, 0, ctx.mm(2000))
        ctx.write(0x6065, 0, 1)
        _enable_mode(ctx, 1)
        ctx.start_sync()
        mark = ctx.frames.mark()
        p0 = mo.last().pos
        ctx.write(0x607A, 0, p0 + _toward_middle(ctx) * ctx.mm(20))
        ctx.write(0x6040, 0, 0x1F)
        ctx.write(0x6040, 0, 0x0F)
        emcy = ctx.wait_emcy(mark, 0x8611, 2.0)
        if emcy is None:
            raise Fail(f"no EMCY 0x8611 (seen {[hex(c) for c in ctx.emcy_codes(mark)]})")
        if not emcy[2] & 0x01:
            raise Fail(f"EMCY 0x8611 with error register 0x{emcy[2]:02X} (bit 0 not set)")
        ctx.wait_sw(0x4F, 0x08, 2.0, "fault state")
        register = ctx.read(0x1001)
        if not register & 0x01:
            raise Fail(f"0x1001 = 0x{register:02X} in fault (bit 0, generic error, not set)")
        code = ctx.read(0x603F)
        hist = ctx.read(0x1003, 1) & 0xFFFF if 0x1003 in ctx.od else 0x8611
        if code != 0x8611 or hist != 0x8611:
            raise Fail(f"0x603F = 0x{code:04X}, 0x1003:1 = 0x{hist:04X}, expected 0x8611")
        mark = ctx.frames.mark()
        ctx.write(0x6040, 0, 0x00)
        ctx.write(0x6040, 0, 0x80)
        ctx.wait_sw(0x4F, 0x40, 1.0, "fault reset (CW bit 7 edge)")
        if ctx.wait_emcy(mark, 0x0000, 0.5) is None:
            raise Fail("no EMCY 0x0000 (error reset) after the fault reset")
        return "EMCY 0x8611, 0x603F / 0x1003 set, reset -> EMCY 0x0000"
    finally:
        mo.close()
        ctx.disable()


# ============================================================================ field behaviours
def _stop_bound(v: float, a: float, reaction_s: float, margin: float) -> float:
    return v * v / (2 * a) + abs(v) * reaction_s + margin


@check("402-FLD-1", "reaction", "CiA 402 (fault reaction option 0x605E = 2: quick-stop ramp 0x6085, 1: slow-down "
       "ramp 0x6084)", "CSP at 100 mm/s (toward the middle of the travel), 0x605E = 2 with 0x6085 = 10 m/s^2 "
       "(0x6084 = 2 m/s^2), then 0x605E = 1 with 0x6084 = 2 m/s^2 (0x6085 = 10 m/s^2); 0x6065 tightened to 1 unit "
       "while moving; the master keeps streaming", "the drive brakes from the ACTUAL speed on the ramp 0x605E "
       "selects: v^2/(4 a) <= travel after the fault <= v^2/(2 a) + v * 20 ms + 1 mm, at rest (< 1 mm/s), then "
       "fault (SW & 0x4F = 0x08)")
def fault_reaction_from_motion(ctx: Context) -> str:
    out = []
    for option, ramp_index, a_mm_s2 in ((2, 0x6085, 10_000), (1, 0x6084, 2_000)):
        out.append(_fault_stop(ctx, option, ramp_index, a_mm_s2))
    return "; ".join(out)


def _fault_stop(ctx: Context, option: int, ramp_index: int, a_mm_s2: float, *, quick_stop: bool = False,
                other_factor: float = 5.0) -> str:
    """CSP at 100 mm/s, 0x605E (``quick_stop``: 0x605A) = ``option`` whose ramp is ``ramp_index`` = ``a_mm_s2``,
    the other ramp ``other_factor`` x steeper or shallower; a following-error fault (``quick_stop``: CW 0x0B in
    the RPDO stream): the travel after it must be that of the ramp (at least half of v^2/2a, at most v^2/2a +
    v * 20 ms + 1 mm), then fault (``quick_stop``: switch on disabled)."""
    mo = Motion(ctx)
    try:
        a = ctx.mm(a_mm_s2)
        other = 0x6084 if ramp_index == 0x6085 else 0x6085
        option_index = 0x605A if quick_stop else 0x605E
        name = f"0x{option_index:04X} = {option}"
        ctx.write(option_index, 0, option)
        ctx.write(ramp_index, 0, a)
        ctx.write(other, 0, ctx.mm(a_mm_s2 * other_factor if ramp_index == 0x6084 else a_mm_s2 / other_factor))
        _enable_mode(ctx, 8)
        p0 = ctx.read(0x6064)
        v_cmd = ctx.mm(100)
        d = _toward_middle(ctx)
        mo.step_units = 0.0
        mo.stream(p0, 0.0)
        for i in range(1, 51):  # ramp to 100 mm/s over 50 SYNC periods (toward the middle of the travel)
            mo.step_units = d * v_cmd * ctx.sync_period_s * i / 50
            mo.pause(ctx.sync_period_s)
        mo.pause(0.25)
        # judge the stop only from speed: wait (up to 2 s of node time) until the axis really runs
        cruise_mark = ctx.frames.mark()
        expired = ctx.deadline(2.0)
        while not expired():
            moving = [s for s in mo.samples(cruise_mark) if s.vel is not None]
            if moving and abs(moving[-1].vel) >= 0.8 * v_cmd:
                break
            time.sleep(0.01)
        mark = ctx.frames.mark()
        if quick_stop:
            mo.cw = 0x0B  # (quick stop: bit 2 = 0, in the stream's next RPDO)
        else:
            if 0x6066 in ctx.od:
                ctx.write(0x6066, 0, 0)
            ctx.write(0x6065, 0, 1)
        stopping = (lambda sw: sw & STATE_MASK != OE) if quick_stop else _is_fault
        expired = ctx.deadline(2.0)
        first = None
        while first is None and not expired():
            first = next((s for s in mo.samples(mark) if stopping(s.sw)), None)
            time.sleep(0.005)
        if first is None:
            raise Fail(f"no {'quick stop' if quick_stop else 'fault'} within 2 s of "
                       f"{'CW 0x0B' if quick_stop else '0x6065 = 1'} while moving at 100 mm/s")
        before = [s for s in mo.samples(mark) if s.t <= first.t and s.vel is not None]
        v_f = abs(before[-1].vel) if before else v_cmd
        if v_f < 0.5 * v_cmd:
            raise Fail(f"the stop came at {v_f / ctx.units_per_mm:.1f} mm/s, below half the commanded "
                       f"{v_cmd / ctx.units_per_mm:.0f} mm/s: the stop from motion cannot be judged")
        mo.pause(1.0)  # (lockstep: 1 s of node time)
        samples = mo.samples(mark)
        last = samples[-1]
        # travelled from the last sample before the stop: a gap in the samples (a node or master descheduled on a
        # loaded host answers the queued SYNCs with the state after it) cannot hide part of the stop
        earlier = [s for s in samples if s.t < first.t]
        start = earlier[-1] if earlier else first
        travel = abs(last.pos - start.pos)
        bound = _stop_bound(v_f, a, 0.020, ctx.mm(1))
        v_end = abs(last.vel or 0)
        ctx.note(f"stop at SW 0x{first.sw:04X} pos {first.pos} v {v_f} (last sample before it: pos {start.pos}); "
                 f"end pos {last.pos} v {v_end}")
        least = 0.5 * v_f * v_f / (2 * a)
        if travel > bound:
            raise Fail(f"{name}: travelled {travel / ctx.units_per_mm:.2f} mm after the stop began from "
                       f"{v_f / ctx.units_per_mm:.0f} mm/s, bound v^2/2a + margin = "
                       f"{bound / ctx.units_per_mm:.2f} mm with 0x{ramp_index:04X} (coasting? another ramp?)")
        if travel < least:
            raise Fail(f"{name}: stopped in {travel / ctx.units_per_mm:.2f} mm from "
                       f"{v_f / ctx.units_per_mm:.0f} mm/s, less than half of v^2/2a = "
                       f"{2 * least / ctx.units_per_mm:.2f} mm with 0x{ramp_index:04X}: not the ramp "
                       f"0x{option_index:04X} selects")
        if v_end > ctx.mm(1):
            raise Fail(f"still moving at {v_end / ctx.units_per_mm:.1f} mm/s 1 s after the stop began")
        expired = ctx.deadline(2.0)
        end_sw, end_name = (0x40, "switch on disabled") if quick_stop else (0x08, "fault")
        while last.sw & 0x4F != end_sw and not expired():  # the reaction ends once the axis is at rest
            time.sleep(0.05)
            last = mo.samples(mark)[-1]
        if last.sw & 0x4F != end_sw:
            raise Fail(f"{name}: SW 0x{last.sw:04X} 3 s after the stop began, expected {end_name} "
                       f"(0x{end_sw:02X})")
        return (f"{name}: {travel / ctx.units_per_mm:.2f} mm from {v_f / ctx.units_per_mm:.0f} mm/s "
                f"(ramp 0x{ramp_index:04X}: {least / ctx.units_per_mm:.2f}..{bound / ctx.units_per_mm:.2f} mm), "
                f"at rest, {end_name}")
    finally:
        mo.close()
        boot(ctx)


@check("402-QS-1", "reaction", "CiA 402 6.1.3 (quick stop, transitions 11, 12; quick stop option 0x605A = 2: "
       "quick-stop ramp 0x6085, 1: slow-down ramp 0x6084)", "CSP at 100 mm/s (toward the middle of the travel), "
       "0x605A = 2 with 0x6085 = 10 m/s^2 (0x6084 = 1 m/s^2), then 0x605A = 1 with 0x6084 = 2 m/s^2 (0x6085 = "
       "10 m/s^2); CW 0x0B (quick stop) in the RPDO stream while moving",
       "the drive brakes from the ACTUAL speed on the ramp 0x605A selects: v^2/(4 a) <= travel after the quick stop "
       "<= v^2/(2 a) + v * 20 ms + 1 mm, at rest (< 1 mm/s), then switch on disabled (SW & 0x4F = 0x40)")
def quick_stop_from_motion(ctx: Context) -> str:
    if 0x605A not in ctx.od:
        raise Skip("the EDS lists no quick stop option code 0x605A")
    out = []
    for option, ramp_index, a_mm_s2, other_factor in ((2, 0x6085, 10_000, 10.0), (1, 0x6084, 2_000, 5.0)):
        out.append(_fault_stop(ctx, option, ramp_index, a_mm_s2, quick_stop=True, other_factor=other_factor))
    return "; ".join(out)


@check("402-FLD-2", "rpdo", "CiA 301 7.2.2 (all PDO entries stored before the application reacts); CiA 402 12 "
       "(new set-point)",
       "PP, old 0x607A = actual + 5 mm by SDO; ONE RPDO1 [CW 0x1F, 0x607A = actual + 20 mm], then [0x0F, same] "
       "(- instead of + when the axis is on the + side of the travel's middle)",
       "the axis moves to actual + 20 mm (the target of the same PDO), not to the old target")
def cw_and_target_in_one_rpdo(ctx: Context) -> str:
    mo = Motion(ctx)
    try:
        p0 = _start_pp(ctx, mo, velocity_mm_s=200)
        d = _toward_middle(ctx)
        stale = p0 + d * ctx.mm(5)
        ctx.write(0x607A, 0, stale)
        new = p0 + d * ctx.mm(20)
        mo.rpdo(0x1F, new)
        ctx.note(f"RPDO1 [1f 00 {new.to_bytes(4, 'little', signed=True).hex(' ')}]")
        ctx.sleep(0.05)
        mo.rpdo(0x0F, new)
        try:
            s = mo.wait(lambda s: s.sw & 0x400 and d * (s.pos - p0) > ctx.mm(1), 2.0, "target reached")
        except Fail:
            s = mo.last()
        ctx.sleep(0.05)
        s = mo.last()
        if abs(s.pos - new) > max(ctx.read(0x6067), ctx.mm(0.05)):
            raise Fail(f"axis at {s.pos} (moved {(s.pos - p0) / ctx.units_per_mm:.2f} mm); the RPDO's target was "
                       f"{new} ({d * 20:+d} mm), the stale one {stale} ({d * 5:+d} mm)")
        return f"moved to {s.pos} ({(s.pos - p0) / ctx.units_per_mm:+.2f} mm)"
    finally:
        mo.close()
        ctx.disable()


def _loss_of_control(ctx: Context, command: int) -> str:
    if 0x6007 not in ctx.od:
        raise Skip("the EDS lists no abort connection option 0x6007")
    mo = Motion(ctx)
    try:
        a = ctx.mm(2000)
        ctx.write(0x6007, 0, 1)
        ctx.write(0x605E, 0, 2)
        ctx.write(0x6085, 0, a)
        ctx.write(0x6083, 0, ctx.mm(2000))
        _enable_mode(ctx, 3)
        ctx.start_sync()
        v_target = _toward_middle(ctx) * ctx.mm(50)
        ctx.write(0x60FF, 0, v_target)
        mo.wait(lambda s: s.vel is not None and abs(s.vel - v_target) < ctx.mm(3), 2.0, "50 mm/s")
        p0 = mo.last().pos
        mark = ctx.frames.mark()
        ctx.nmt(command)
        ctx.sleep(0.5)  # (lockstep: 0.5 s of node time)
        if command == 0x82:
            if ctx.frames.wait(mark, ctx.hb_cob, lambda d: d[:1] == b"\x00", 1.0) is None:
                raise Fail("no boot-up after reset communication")
        else:
            ctx.nmt(0x01)
            time.sleep(0.05)
        p1 = ctx.read(0x6064)
        v1 = ctx.read(0x606C)
        sw = ctx.read(0x6041)
        travel = abs(p1 - p0)
        bound = _stop_bound(ctx.mm(50), a, 0.1, ctx.mm(1))
        name = "NMT Stop" if command == 0x02 else "NMT Reset Communication"
        if travel > bound or abs(v1) > ctx.mm(1):
            raise Fail(f"{name} at 50 mm/s with 0x6007 = 1: travelled {travel / ctx.units_per_mm:.1f} mm in 0.5 s, "
                       f"velocity {v1 / ctx.units_per_mm:.1f} mm/s (bound {bound / ctx.units_per_mm:.1f} mm, at rest)")
        if sw & 0x4F != 0x08:
            raise Fail(f"SW 0x{sw:04X} after {name} with 0x6007 = 1 (fault), expected fault")
        return f"{name}: {travel / ctx.units_per_mm:.2f} mm, at rest, fault 0x{ctx.read(0x603F):04X}"
    finally:
        mo.close()
        boot(ctx)


@check("402-FLD-3", "loss", "CiA 402 (0x6007 abort connection option: NMT Stopped is a loss of control)",
       "PV at 50 mm/s, 0x6007 = 1, NMT Stop; after 0.5 s NMT Start and read",
       "the axis stopped (travel <= v^2/2a + v * 0.1 s + 1 mm, at rest) and is in fault")
def loss_nmt_stop(ctx: Context) -> str:
    return _loss_of_control(ctx, 0x02)


@check("402-FLD-4", "loss", "CiA 402 (0x6007; NMT Reset Communication)",
       "PV at 50 mm/s, 0x6007 = 1, NMT Reset Communication", "the axis stopped and is in fault")
def loss_nmt_reset_comm(ctx: Context) -> str:
    return _loss_of_control(ctx, 0x82)


INJ_INJECT, INJ_CLEAR, INJ_DUTY, INJ_MAG, INJ_ALLOWED = 0x5FF0, 0x5FF1, 0x5FF2, 0x5FF4, 0x5FF6
LIMIT_SWITCH_KIND = 7


def _injection_offered(ctx: Context) -> None:
    if INJ_ALLOWED not in ctx.od:
        raise Skip("a generic node cannot be forced onto a limit switch and this one offers no fault-injection "
                   "channel (0x5FF0..0x5FF6 not in the EDS)")
    try:
        allowed = ctx.read(INJ_ALLOWED)
    except canopen.SdoAbortedError as exc:
        raise Skip(f"fault-injection channel not readable (0x{exc.code:08X})") from None
    if not allowed:
        raise Skip("the node's fault-injection channel is off (0x5FF6 = 0; virtualaxis: serve "
                   "--allow-fault-injection), so no limit switch can be forced")


@check("402-FLD-5", "limits", "CiA 402 (0x60FD digital inputs; hardware limit switch stops in every mode)",
       "in each supported mode of PP, PV, CSP, CSV, CST moving + at 30 mm/s: positive limit "
       "switch forced through the fault-injection channel", "the axis stops (travel <= v^2/(2 0x6085) + v * 50 ms + "
       "1 mm, at rest), 0x60FD bit 1, fault or warning (SW bit 7 / 11)")
def limit_switch_every_mode(ctx: Context) -> str:
    boot(ctx)
    _injection_offered(ctx)
    supported = ctx.read(0x6502)
    done = []
    for mode in (1, 3, 8, 9, 10):
        if not supported & MODE_BITS[mode]:
            continue
        done.append(_limit_switch_in(ctx, mode))
    if not done:
        raise Skip("none of PP, PV, CSP, CSV, CST supported")
    return "; ".join(done)


def _start_positive(ctx: Context, mo: Motion, mode: int, p0: int, v: int) -> None:
    """Start motion in the + direction in ``mode`` (enabled): CSP streams set-points from ``p0`` at ``v``
    (inc/s); PP moves to ``p0`` + 200 mm; PV/CSV command ``v``; the torque modes 15 % rated torque."""
    if mode == 8:
        mo.stream(p0, v)
        return
    ctx.start_sync()
    if mode == 1:
        ctx.write(0x607A, 0, p0 + ctx.mm(200))
        ctx.write(0x6040, 0, 0x1F)
        ctx.write(0x6040, 0, 0x0F)
    elif mode in (3, 9):
        ctx.write(0x60FF, 0, v)
    else:
        ctx.write(0x6071, 0, 150)  # 15 % rated torque


def _limit_switch_in(ctx: Context, mode: int) -> str:
    mo = Motion(ctx)
    name = MODES[mode]
    try:
        a = ctx.mm(5000)
        ctx.write(0x6085, 0, a)
        ctx.write(0x6083, 0, ctx.mm(2000))
        ctx.write(0x6084, 0, ctx.mm(2000))
        ctx.write(0x6081, 0, ctx.mm(30))
        # the injection's options before the move: only the inject write itself lies between the last sample
        # before the switch and the switch (three SDO round trips there took > 100 ms on a loaded machine)
        ctx.write(INJ_MAG, 0, 1)
        ctx.write(INJ_DUTY, 0, 0)
        _enable_mode(ctx, mode)
        p0 = ctx.read(0x6064)
        v = ctx.mm(30)
        _start_positive(ctx, mo, mode, p0, v)
        try:
            mo.wait(lambda s: s.vel is not None and s.vel > ctx.mm(5), 2.0, f"{name}: motion +")
        except Fail as exc:
            raise Fail(f"{name}: the axis did not move + before the switch was forced ({exc})") from None
        ctx.sleep(0.05)
        s0 = mo.last()
        v0 = max(s0.vel or v, v)
        ctx.write(INJ_INJECT, 0, LIMIT_SWITCH_KIND)
        ctx.sleep(0.15)
        s1, v_rest = mo.at_rest_velocity()
        inputs = ctx.read(0x60FD)
        travel = s1.pos - s0.pos
        bound = _stop_bound(v0, a, 0.05, ctx.mm(1)) + abs(v0) * 0.05
        if travel > bound or abs(v_rest) > ctx.mm(1):
            raise Fail(f"{name}: {travel / ctx.units_per_mm:.1f} mm past the forced + limit switch, velocity "
                       f"{v_rest / ctx.units_per_mm:.1f} mm/s (mean of 20 SYNC periods) "
                       f"(bound {bound / ctx.units_per_mm:.1f} mm, at rest)")
        if not inputs & 0x2:
            raise Fail(f"{name}: 0x60FD = 0x{inputs:08X}, positive limit switch bit 1 not shown")
        if not (_is_fault(s1.sw) or s1.sw & 0x880):
            raise Fail(f"{name}: SW 0x{s1.sw:04X}: neither fault nor warning / internal limit at the switch")
        return f"{name}: {travel / ctx.units_per_mm:.2f} mm, SW 0x{s1.sw:04X}"
    finally:
        try:
            ctx.write(INJ_CLEAR, 0, LIMIT_SWITCH_KIND)
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError):
            pass
        mo.close()
        boot(ctx)


# ============================================================================ PP halt, software limits, fault reset
def _toward_middle(ctx: Context) -> int:
    """+1 or -1: the direction from the present position toward the middle of the travel, where a check has
    room to move (NMT Reset Node does not move the axis back, and an earlier check or run may have left it
    near an end): toward the middle of the software limits 0x607D when both are set (finite, not the full
    32-bit range), else toward 0."""
    pos = ctx.read(0x6064)
    middle = 0
    if 0x607D in ctx.od:
        try:
            lo, hi = ctx.read(0x607D, 1), ctx.read(0x607D, 2)
        except canopen.SdoAbortedError:
            lo, hi = 0, 0
        if -2**31 < lo < hi < 2**31 - 1:
            middle = (lo + hi) // 2
    return -1 if pos > middle else 1


def _pp_to(ctx: Context, mo: Motion, target: int, timeout: float) -> Sample:
    """A PP move to ``target`` (mode 1 enabled, SYNC running); returns the sample at target reached."""
    ctx.write(0x607A, 0, target)
    ctx.write(0x6040, 0, 0x1F)
    ctx.wait_sw(0x1000, 0x1000, 0.5, "set-point acknowledge (bit 12)")
    ctx.write(0x6040, 0, 0x0F)
    return mo.wait(lambda s: s.sw & 0x400 and abs(s.pos - target) < ctx.mm(0.5), timeout, f"PP target {target}")


@check("402-PP-2", "modes", "CiA 402 6.2 / 12 (controlword bit 8 halt in profile position, 0x605D); CL 19",
       "PP 40 mm toward the middle at 100 mm/s; CW 0x11F after 0.1 s",
       "at rest (|0x606C| < 1 mm/s) within 0.5 s, short of the target, bit 10 = 1 (halted at standstill)")
def pp_halt(ctx: Context) -> str:
    mo = Motion(ctx)
    try:
        p0 = _start_pp(ctx, mo, velocity_mm_s=100)
        target = p0 + _toward_middle(ctx) * ctx.mm(40)
        ctx.write(0x607A, 0, target)
        ctx.write(0x6040, 0, 0x1F)
        ctx.sleep(0.1)
        ctx.write(0x6040, 0, 0x11F)
        s = mo.wait(lambda s: s.vel is not None and abs(s.vel) < ctx.mm(1) and s.sw & 0x400, 0.8,
                    "standstill with bit 10 after halt")
        ctx.sleep(0.05)
        s = mo.last()
        if abs(s.pos - p0) < ctx.mm(1):
            raise Fail(f"the move did not start before the halt (position {s.pos}, start {p0})")
        if abs(target - s.pos) < ctx.mm(10):
            raise Fail(f"halt did not stop the move short of the target ({s.pos}, target {target})")
        return f"halted at {s.pos} ({(s.pos - p0) / ctx.units_per_mm:+.1f} mm of 40), SW 0x{s.sw:04X}"
    finally:
        mo.close()
        ctx.disable()


@check("402-PP-3", "modes", "CiA 402 12.3 (0x607D software position limits, SW bit 11 internal limit); CL 25",
       "0x607D = actual -/+ 5 mm (the move side) and +/- 1 m; PP target 20 mm beyond it",
       "the axis stays within 0x607D (+ 0x6067); SW bit 11, or fault with EMCY 0x8612")
def software_limit(ctx: Context) -> str:
    if 0x607D not in ctx.od:
        raise Skip("the EDS lists no software position limits 0x607D")
    mo = Motion(ctx)
    try:
        ctx.write(0x6081, 0, ctx.mm(100))
        ctx.write(0x6083, 0, ctx.mm(2000))
        ctx.write(0x6084, 0, ctx.mm(2000))
        d = _toward_middle(ctx)
        p0 = ctx.read(0x6064)
        limit = p0 + d * ctx.mm(5)
        lo, hi = (p0 - ctx.mm(1000), limit) if d > 0 else (limit, p0 + ctx.mm(1000))
        try:
            ctx.write(0x607D, 1, lo)
            ctx.write(0x607D, 2, hi)
        except canopen.SdoAbortedError as exc:
            raise Skip(f"0x607D not writable (0x{exc.code:08X})") from None
        _enable_mode(ctx, 1)
        ctx.start_sync()
        mark = ctx.frames.mark()
        target = p0 + d * ctx.mm(25)
        ctx.write(0x607A, 0, target)
        ctx.write(0x6040, 0, 0x1F)
        ctx.sleep(0.4)
        s = mo.last()
        window = max(ctx.read(0x6067), ctx.mm(0.05))
        beyond = (s.pos - limit) * d
        em = ctx.wait_emcy(mark, 0x8612, 0.05)
        if beyond > window:
            raise Fail(f"moved to {s.pos}, {beyond} units beyond the 0x607D limit {limit} (target {target})")
        if not (s.sw & 0x800 or (_is_fault(s.sw) and em is not None)):
            raise Fail(f"SW 0x{s.sw:04X}: neither bit 11 (internal limit) nor fault with EMCY 0x8612 for a target "
                       "beyond 0x607D")
        return f"stopped at {s.pos} (limit {limit}, target {target}), SW 0x{s.sw:04X}"
    finally:
        mo.close()
        boot(ctx)


@check("402-FLT-1", "reaction", "CiA 402 6.1.3 (transitions 13, 14, 15: fault reset only on a rising edge of "
       "CW bit 7); 0x603F; CiA 301 0x1003, EMCY; CL 15, 16",
       "following error in PP (0x6065 = 1); then CW 0x0F and 0x00 (no edge); then CW 0x80",
       "fault; EMCY code = 0x603F = 0x1003:1 low word; no reset without the edge; the edge -> switch on disabled "
       "and EMCY 0x0000")
def fault_reset_edge(ctx: Context) -> str:
    mo = Motion(ctx)
    try:
        ctx.write(0x6081, 0, ctx.mm(50))
        ctx.write(0x6065, 0, 1)
        _enable_mode(ctx, 1)
        ctx.start_sync()
        mark = ctx.frames.mark()
        p0 = mo.last().pos
        ctx.write(0x607A, 0, p0 + _toward_middle(ctx) * ctx.mm(5))
        ctx.write(0x6040, 0, 0x1F)
        ctx.write(0x6040, 0, 0x0F)
        ctx.wait_sw(0x4F, 0x08, 2.0, "fault after a following error")
        codes = [c for c in ctx.emcy_codes(mark) if c]
        if not codes:
            raise Fail("fault without an EMCY")
        code = ctx.read(0x603F)
        hist = ctx.read(0x1003, 1) & 0xFFFF if 0x1003 in ctx.od else code
        if not (code == hist == codes[-1]):
            raise Fail(f"EMCY 0x{codes[-1]:04X}, 0x603F = 0x{code:04X}, 0x1003:1 = 0x{hist:04X}: not the same code")
        for cw in (0x0F, 0x00):
            ctx.write(0x6040, 0, cw)
            ctx.sleep(0.05)
            sw = ctx.sw()
            if sw & 0x4F != 0x08:
                raise Fail(f"left fault without a rising edge of CW bit 7 (CW 0x{cw:02X} -> SW 0x{sw:04X})")
        mark = ctx.frames.mark()
        ctx.write(0x6040, 0, 0x80)
        ctx.wait_sw(0x4F, 0x40, 1.0, "fault reset (CW bit 7 edge)")
        if ctx.wait_emcy(mark, 0x0000, 0.5) is None:
            raise Fail("no EMCY 0x0000 (error reset) after the fault reset")
        return f"fault 0x{code:04X} (EMCY = 0x603F = 0x1003:1); stays in fault on 0x0F / 0x00; reset on 0x80 + EMCY 0"
    finally:
        mo.close()
        boot(ctx)


@check("402-FLT-2", "reaction", "CiA 402 6.1.3 (transition 15 only on the rising edge of CW bit 7); CL 16",
       "PP enabled with CW bit 7 already set (0x8F), a following error (0x6065 = 1) with bit 7 held (0x9F, 0x8F), "
       "then 0x8F again, then 0x0F and 0x8F", "fault; it stays while bit 7 stays high; the edge resets it")
def fault_reset_needs_an_edge(ctx: Context) -> str:
    mo = Motion(ctx)
    try:
        ctx.write(0x6081, 0, ctx.mm(50))
        ctx.write(0x6065, 0, 1)
        _enable_mode(ctx, 1)
        ctx.start_sync()
        ctx.write(0x6040, 0, 0x8F)
        ctx.sleep(0.05)
        if ctx.sw() & 0x6F != 0x27:
            raise Skip("the node leaves OPERATION ENABLED on CW 0x8F (bit 7 outside FAULT): the fault cannot be "
                       "provoked with bit 7 held")
        p0 = mo.last().pos
        ctx.write(0x607A, 0, p0 + _toward_middle(ctx) * ctx.mm(5))
        ctx.write(0x6040, 0, 0x9F)
        ctx.write(0x6040, 0, 0x8F)
        ctx.wait_sw(0x4F, 0x08, 2.0, "fault after a following error (CW bit 7 held)")
        for _ in range(3):
            ctx.write(0x6040, 0, 0x8F)
            ctx.sleep(0.05)
            sw = ctx.sw()
            if sw & 0x4F != 0x08:
                raise Fail(f"left fault with CW bit 7 held high, without a rising edge (SW 0x{sw:04X})")
        ctx.write(0x6040, 0, 0x0F)
        ctx.write(0x6040, 0, 0x8F)
        ctx.wait_sw(0x4F, 0x40, 1.0, "fault reset (CW bit 7 edge)")
        return "stays in fault while bit 7 is held; the rising edge resets it"
    finally:
        mo.close()
        boot(ctx)


@check("402-CSP-2", "modes", "CiA 402 (cyclic synchronous position: the target of SYNC k drives cycle k); CL 22",
       "lockstep: CSP, 0x60C2 = one SYNC period, TPDO2 = position demand 0x6062; RPDO1 target step of 0.1 mm "
       "before SYNC k", "the answer to SYNC k shows the old demand, the answer to SYNC k + 1 the new target")
def csp_target_at_its_sync(ctx: Context) -> str:
    if not ctx.lockstep:
        raise Skip("needs a node in SYNC lockstep (--pacing lockstep): in real time the cycle a target lands in "
                   "depends on the host")
    if 0x6062 not in ctx.od and 0x60FC not in ctx.od:
        raise Skip("the EDS lists no position demand value (0x6062 / 0x60FC)")
    demand = 0x6062 if 0x6062 in ctx.od else 0x60FC
    mo = Motion(ctx)
    try:
        ctx.nmt(0x80)
        time.sleep(0.03)
        mo.map(0x1801, 0x1A01, mo.tpdo2, [(demand << 16) | 0x20], 1)
        mo.map(0x1400, 0x1600, mo.rpdo1, [0x60400010, 0x607A0020], 1)  # synchronous: applied at the SYNC
        ctx.write(0x1006, 0, round(ctx.sync_period_s * 1e6))
        if 0x60C2 in ctx.od:
            ctx.write(0x60C2, 1, round(ctx.sync_period_s * 1e3))
            ctx.write(0x60C2, 2, -3)
        ctx.nmt(0x01)
        time.sleep(0.03)
        _enable_mode(ctx, 8)
        p0 = ctx.read(0x6064)

        def answer(target: int) -> tuple[int, int]:
            """RPDO1 (CW 0x0F, target), one SYNC; (position demand, position) of its answer."""
            mark = ctx.frames.mark()
            mo.rpdo(0x0F, target)
            ctx.sync_once()
            f1 = ctx.frames.wait(mark, mo.tpdo1, None, 2.0)
            f2 = ctx.frames.wait(mark, mo.tpdo2, None, 2.0)
            if f1 is None or f2 is None:
                raise Fail("no TPDO1 / TPDO2 answer to a SYNC within 2 s")
            return (int.from_bytes(f2[2][0:4], "little", signed=True),
                    int.from_bytes(f1[2][2:6], "little", signed=True))

        for _ in range(5):
            answer(p0)
        step = _toward_middle(ctx) * ctx.mm(0.1)
        got_k = answer(p0 + step)
        got_k1 = answer(p0 + step)
        ctx.note(f"demand / position: SYNC k {got_k}, SYNC k+1 {got_k1}; target {p0} -> {p0 + step}")
        tol = max(1, abs(step) // 20)
        if abs(got_k[0] - p0) > tol:
            raise Fail(f"the answer to SYNC k (values before its cycle) shows demand {got_k[0]}, expected the old "
                       f"{p0}")
        if abs(got_k1[0] - (p0 + step)) > tol:
            raise Fail(f"the answer to SYNC k + 1 shows demand {got_k1[0]}, expected the target {p0 + step} of "
                       "SYNC k (applied a SYNC late?)")
        return f"demand {got_k[0]} -> {got_k1[0]} in the cycle of the SYNC that carried the target"
    finally:
        mo.close()
        ctx.disable()
        boot(ctx)


# ============================================================================ real hardware limit switches
@check("402-FLD-6", "limits", "CiA 402 (0x60FD bit 1 positive limit switch; the drive stops in every mode)",
       "0x607D max widened by 20 % (if finite); the axis driven onto the REAL + switch in PV "
       "(search), then from a few mm before it in PP, PT, CSP, CSV, CST (each supported one); then PV away",
       "0x60FD bit 1; the axis stops (travel past the switch <= v^2/(2 0x6085) + v * 50 ms + 1 mm, at rest), fault "
       "or warning (SW bit 3 / 7 / 11); the axis can move away from the switch")
def real_limit_switch_every_mode(ctx: Context) -> str:
    if 0x60FD not in ctx.od:
        raise Skip("the EDS lists no digital inputs 0x60FD (limit switches not visible)")
    boot(ctx)
    supported = ctx.read(0x6502)
    if not supported & MODE_BITS[3]:
        raise Skip("profile velocity (the search mode) not supported")
    x_sw = None
    done = []
    mo = Motion(ctx)
    try:
        a = ctx.mm(5000)
        ctx.write(0x6085, 0, a)
        ctx.write(0x6083, 0, ctx.mm(5000))
        ctx.write(0x6084, 0, ctx.mm(5000))
        lo, hi = (ctx.read(0x607D, 1), ctx.read(0x607D, 2)) if 0x607D in ctx.od else (-2**31, 2**31 - 1)
        if hi < 2**31 - 1 and lo > -2**31:  # finite software limits: widen the maximum by 20 % of the range
            ctx.write(0x607D, 2, min(hi + (hi - lo) // 5, 2**31 - 1))
        for mode in (3, 1, 4, 8, 9, 10):
            if supported & MODE_BITS[mode]:
                res, x_sw = _onto_switch(ctx, mo, mode, x_sw, a, hi if hi < 2**31 - 1 and lo > -2**31 else None)
                done.append(res)
    finally:
        mo.close()
        boot(ctx)
    return "; ".join(done)


def _onto_switch(ctx: Context, mo: Motion, mode: int, x_sw: int | None, a: int,
                 soft_max: int | None = None) -> tuple[str, int]:
    """Drive onto the + switch in ``mode`` (approach first if ``x_sw`` is known and far), check the stop,
    move away in PV. Returns the result text and the switch position [units]."""
    name = MODES[mode]
    try:
        ctx.write(0x6040, 0, 0x00)
        ctx.wait_sw(0x4F, 0x40, 1.0, "switch on disabled before the mode change")
        p_start = ctx.read(0x6064)
        if x_sw is not None and x_sw - p_start > ctx.mm(20):  # approach: PP to 5 mm before the switch found
            ctx.write(0x6081, 0, ctx.mm(200))
            _enable_mode(ctx, 1)
            ctx.start_sync()
            _pp_to(ctx, mo, x_sw - ctx.mm(5), 3.0)
            ctx.write(0x6040, 0, 0x06)
            ctx.wait_sw(STATE_MASK, RTSO, 1.0, "ready to switch on before the mode change")
        if x_sw is not None:
            v, timeout = ctx.mm(50), 1.0
        else:
            vmax = ctx.read(0x607F) if 0x607F in ctx.od else ctx.mm(500)
            v, timeout = min(int(vmax * 0.5), ctx.mm(300)), 3.0
        ctx.write(0x6081, 0, v)
        ctx.stop_sync()
        _enable_mode(ctx, mode)
        p0 = ctx.read(0x6064)
        mark = ctx.frames.mark()
        if ctx.read(0x60FD) & 0x2:
            raise Fail(f"{name}: + limit switch already active at {p0} before the move")
        _start_positive(ctx, mo, mode, p0, v)
        expired = ctx.deadline(timeout)  # (lockstep: node time, in SYNCs)
        hit = None
        while hit is None and not expired():
            time.sleep(0.02)
            if ctx.poll(0x60FD) & 0x2:
                hit = mo.samples(mark)
        if hit is None:
            ctx.note(f"no switch: 0x6064 = {ctx.read(0x6064)}, 0x606C = {ctx.read(0x606C)}, SW 0x{ctx.sw():04X}")
            if x_sw is None:
                pos = ctx.read(0x6064)
                if soft_max is not None and pos > soft_max:
                    raise Fail(f"{name}: the axis ran to {pos}, {(pos - soft_max) / ctx.units_per_mm:.1f} mm past "
                               f"its software limit 0x607D:2 = {soft_max}, with no + limit switch in 0x60FD "
                               f"({(pos - p0) / ctx.units_per_mm:.0f} mm travelled)")
                raise Skip(f"no + limit switch (0x60FD bit 1) met within {timeout:g} s at "
                           f"{v / ctx.units_per_mm:.0f} mm/s from {p0} (the axis reached {pos}, inside its "
                           "software limits)")
            raise Fail(f"{name}: 0x60FD bit 1 not set although the axis reached {ctx.read(0x6064)} "
                       f"(switch found at {x_sw})")
        ctx.sleep(0.15)
        s1, v_rest = mo.at_rest_velocity()
        inputs = ctx.read(0x60FD)
        moving = [s for s in hit if s.vel is not None]
        v0 = max(abs(moving[-1].vel), v) if moving else v
        x_at = hit[-1].pos if hit else p0
        found = x_sw if x_sw is not None else x_at
        travel = s1.pos - x_at
        bound = _stop_bound(v0, a, 0.05, ctx.mm(1)) + abs(v0) * 0.02  # + the 20 ms SDO poll of 0x60FD
        if travel > bound or abs(v_rest) > ctx.mm(1):
            raise Fail(f"{name}: {travel / ctx.units_per_mm:.1f} mm past the + limit switch from "
                       f"{v0 / ctx.units_per_mm:.0f} mm/s, velocity {v_rest / ctx.units_per_mm:.1f} mm/s "
                       "(mean of 20 SYNC periods) "
                       f"(bound {bound / ctx.units_per_mm:.1f} mm, at rest)")
        if not inputs & 0x2:
            raise Fail(f"{name}: 0x60FD = 0x{inputs:08X} at the switch: bit 1 not set")
        if not (_is_fault(s1.sw) or s1.sw & 0x880):
            raise Fail(f"{name}: SW 0x{s1.sw:04X}: neither fault nor warning / internal limit at the switch")
        mo.stop_stream()
        # move away: targets to zero, fault reset if needed (once more if the fault comes back while the axis
        # settles on the switch), PV backwards
        ctx.write(0x6040, 0, 0x00)
        ctx.start_sync()
        ctx.write(0x60FF, 0, 0)
        if mode in (4, 10):
            ctx.write(0x6071, 0, 0)
        ctx.sleep(0.05)
        try:
            _enable_mode(ctx, 3)
        except Fail as exc:
            ctx.note(f"{name}: enable for the move away: {exc}; once more")
            ctx.sleep(0.2)
            try:
                _enable_mode(ctx, 3)
            except Fail as exc2:
                raise Fail(f"{name}: cannot enable PV to move away from the + switch: {exc2}") from None
        x1 = ctx.read(0x6064)
        ctx.write(0x60FF, 0, -ctx.mm(50))
        # away until the switch has released and the axis is 5 mm back (judged on the axis, not on a wall-clock
        # time: a loaded master or a lockstep drive advances less plant time per second), at most 2 s
        expired = ctx.deadline(2.0)
        x2 = x1
        while not expired():
            time.sleep(0.02)
            x2 = ctx.read(0x6064)
            if x1 - x2 >= ctx.mm(5) and not ctx.read(0x60FD) & 0x2:
                break
        ctx.note(f"away: SW 0x{ctx.sw():04X}, 0x606C = {ctx.read(0x606C)}, 0x60FD = 0x{ctx.read(0x60FD):X}")
        ctx.write(0x60FF, 0, 0)
        if x1 - x2 < ctx.mm(2):
            raise Fail(f"{name}: could not move away from the + limit switch in PV (0x6064 {x1} -> {x2})")
        if ctx.read(0x60FD) & 0x2:
            raise Fail(f"{name}: + limit switch still active {(x1 - x2) / ctx.units_per_mm:.1f} mm away from where "
                       "the axis stopped on it")
        return (f"{name}: {travel / ctx.units_per_mm:.2f} mm past the switch at {x_at}, SW 0x{s1.sw:04X}, "
                f"away {(x2 - x1) / ctx.units_per_mm:.1f} mm", found)
    finally:
        mo.stop_stream()
