"""The CANopen master of the latency benchmarks (``bench_drive_latency.py``, ``bench_side_channels.py``).

The drive runs in its own ``virtualaxis serve`` process on a host-local ``udp_multicast`` bus (hop_limit 0);
the benchmark process is the master: it sends a synchronous CSP target RPDO per axis and a SYNC every period
(:func:`sync_loop`) and pairs the SYNCs with the synchronous TPDOs the drive answers (:func:`latency_stats`).

Where the times come from (all ``time.time`` seconds, CLOCK_REALTIME, so comparable across processes):

- ``TpdoClock.times[cob]``: the **kernel receive timestamps** (SO_TIMESTAMPNS, set by python-can's
  ``udp_multicast``) of the master's socket. A TPDO's time is therefore the instant it reached the master's
  socket, not the instant the master's (possibly starved) receive thread got to it.
- ``TpdoClock.times[0x080]`` (when asked for): the master's own SYNC as looped back by the kernel (a plain
  ``udp_multicast`` bus receives its own frames), i.e. the instant the SYNC was on the "wire" -- the same
  instant (same loopback pass) at which the drive's socket got it. Latency against this reference contains
  nothing of the master's user-space send path.
- :func:`sync_loop` also returns the master's user-space time right before each ``send`` (the reference the
  benchmarks used before; ``user -> wire`` is the master's own send delay, reported apart).
"""

from __future__ import annotations

import os
import platform
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import can
import numpy as np

REPO = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-c", "import sys; from virtualaxis.cli.main import main; sys.exit(main())"]
SYNC_COB = 0x080


# ------------------------------------------------------------------------------------------ machine / processes
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_port(port: int, timeout_s: float = 10.0) -> None:
    end = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            if time.monotonic() > end:
                raise
            time.sleep(0.02)


def _cpu_model() -> str:
    try:
        for line in subprocess.run(["lscpu"], capture_output=True, text=True).stdout.splitlines():
            if line.startswith("Model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def machine_info() -> dict:
    return {
        "nproc": os.cpu_count(),
        "cpu": _cpu_model(),
        "python": platform.python_version(),
        "load_average_at_end": os.getloadavg(),
    }


def _reference_work(n: int = 1500) -> int:
    """A fixed piece of plain Python (no virtualaxis code): the host's own speed and jitter for a workload of the
    drive cycle's size (~50-150 us)."""
    s = 0
    for i in range(n):
        s += i * i
    return s


def host_jitter(seconds: float = 3.0, period_s: float = 0.001, rt_priority: int = 0) -> dict:
    """How much this host stretches a fixed Python workload (:func:`_reference_work`, written apart from the
    package) that runs once per ``period_s`` as a drive cycle does, against the same workload back to back.
    ``paced_p99_over_p50`` near 1 on a quiet dedicated core; a shared virtual CPU stretches 1 % of the paced runs
    by 5-15x. Every latency figure of a host carries this tail: state it beside them, as ``--cycle-cost``.
    ``rt_priority``: the measuring thread at SCHED_FIFO (as ``serve --rt-priority``); also reports the lateness
    of a plain ``time.sleep`` wake-up to each period."""
    if rt_priority:
        old = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(rt_priority))
    try:
        n = int(seconds / period_s)
        back = np.empty(n)
        for k in range(n):
            t0 = time.perf_counter()
            _reference_work()
            back[k] = time.perf_counter() - t0
            if k >= n // 2:  # (back to back: half as many runs are plenty)
                back = back[:k + 1]
                break
        paced = np.empty(n)
        wake = np.empty(n)
        t = time.perf_counter() + period_s
        for k in range(n):
            d = t - time.perf_counter()
            if d > 0:
                time.sleep(d)
            t0 = time.perf_counter()
            wake[k] = t0 - t
            _reference_work()
            paced[k] = time.perf_counter() - t0
            t += period_s
    finally:
        if rt_priority:
            os.sched_setscheduler(0, old[0], old[1])
    b, p, w = back[50:] * 1e6, paced[50:] * 1e6, wake[50:] * 1e6
    return {
        "period_us": period_s * 1e6,
        "rt_priority": rt_priority,
        "work_us_p50_back_to_back": float(np.percentile(b, 50)),
        "work_us_p99_back_to_back": float(np.percentile(b, 99)),
        "work_us_p50_paced": float(np.percentile(p, 50)),
        "work_us_p99_paced": float(np.percentile(p, 99)),
        "work_us_max_paced": float(p.max()),
        "paced_p99_over_p50": float(np.percentile(p, 99) / np.percentile(b, 50)),
        "wake_late_us_p99": float(np.percentile(w, 99)),
        "wake_late_us_max": float(w.max()),
    }


def _stall_probe(cpu: int, seconds: float, rt_priority: int, out) -> None:
    """One CPU's part of :func:`host_stalls`: :func:`_reference_work` back to back on ``cpu`` for ``seconds``,
    start time and duration of every run sent through ``out``. A 10 ms sleep every 200 runs keeps a SCHED_FIFO
    thread clear of the kernel's real-time throttling."""
    os.sched_setaffinity(0, {cpu})
    if rt_priority:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(rt_priority))
    starts, runs = [], []
    end = time.perf_counter() + seconds
    k = 0
    while True:
        t0 = time.perf_counter()
        if t0 >= end:
            break
        _reference_work()
        starts.append(t0)
        runs.append(time.perf_counter() - t0)
        k += 1
        if k % 200 == 0:
            time.sleep(0.01)
    out.send((np.asarray(starts), np.asarray(runs)))
    out.close()


def host_stalls(seconds: float = 5.0, rt_priority: int = 0, slow_factor: float = 3.0) -> dict:
    """Whether the host slows this whole machine at once: :func:`_reference_work` back to back in one process per
    CPU (pinned; SCHED_FIFO ``rt_priority``), every run slower than ``slow_factor`` x its CPU's median counted.
    Slow runs on different CPUs within 2 ms of each other are one event of the machine (a hypervisor that
    deschedules or shares the virtual CPUs), not of a process or a core; slow runs within 20 ms of each other are
    one burst. Reports the bursts (length, the speed the first CPU kept through them) and the share of slow runs
    that another CPU saw too. No sleeping is timed: a stretch here is not a wake-up from idle."""
    import multiprocessing as mp

    cpus = sorted(os.sched_getaffinity(0))
    ctx = mp.get_context("spawn")
    pipes, procs = [], []
    for cpu in cpus:
        recv, send = ctx.Pipe(duplex=False)
        proc = ctx.Process(target=_stall_probe, args=(cpu, seconds, rt_priority, send))
        proc.start()
        pipes.append(recv)
        procs.append(proc)
    data = [r.recv() for r in pipes]
    for proc in procs:
        proc.join()
    slow = []
    per_cpu = []
    for cpu, (starts, runs) in zip(cpus, data, strict=True):
        med = float(np.median(runs))
        mask = runs > slow_factor * med
        slow.append(starts[mask])
        per_cpu.append({"cpu": cpu, "runs": len(runs), "work_us_p50": med * 1e6,
                        "work_us_p99": float(np.percentile(runs, 99)) * 1e6, "work_us_max": float(runs.max()) * 1e6,
                        "slow_runs": int(mask.sum())})
    coincident = 0
    if len(slow) > 1 and len(slow[0]) and any(len(s) for s in slow[1:]):
        others = np.sort(np.concatenate(slow[1:]))
        for t in slow[0]:
            i = np.searchsorted(others, t)
            near = [abs(others[j] - t) for j in (i - 1, i) if 0 <= j < len(others)]
            coincident += bool(near) and min(near) < 0.002
    starts, runs = data[0]
    med = float(np.median(runs))
    idx = np.flatnonzero(runs > slow_factor * med)
    bursts = []
    if len(idx):
        for g in np.split(idx, np.flatnonzero(np.diff(starts[idx]) > 0.02) + 1):
            span = starts[g[-1]] + runs[g[-1]] - starts[g[0]]
            bursts.append({"at_s": float(starts[g[0]] - starts[0]), "length_ms": float(span * 1e3),
                           "slow_runs": len(g), "speed_kept": float((g[-1] - g[0] + 1) * med / span)})
    wall = float(starts[-1] + runs[-1] - starts[0])
    return {
        "seconds": wall,
        "rt_priority": rt_priority,
        "cpus": per_cpu,
        "slow_runs_seen_by_another_cpu": f"{coincident} of {len(slow[0])}" if len(cpus) > 1 else "one CPU",
        "bursts": bursts,
        "time_in_bursts": float(sum(b["length_ms"] for b in bursts) * 1e-3 / wall),
    }


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid`` [s]."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def set_priority(pid: int, priority: int) -> None:
    """SCHED_FIFO ``priority`` for ``pid`` and all its threads (0: SCHED_OTHER)."""
    policy, param = (os.SCHED_FIFO, priority) if priority else (os.SCHED_OTHER, 0)
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            os.sched_setscheduler(int(tid), policy, os.sched_param(param))
        except OSError:
            pass


def set_affinity(pid: int, cpus: set[int] | None) -> None:
    """CPU affinity of ``pid`` and all its threads (None: leave alone)."""
    if cpus is None:
        return
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            os.sched_setaffinity(int(tid), cpus)
        except OSError:
            pass


def children(pid: int) -> list[int]:
    out = []
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            out += [int(c) for c in Path(f"/proc/{pid}/task/{tid}/children").read_text().split()]
        except OSError:
            pass
    return out


def thread_schedstat(pid: int) -> dict[str, list[float]]:
    """Per thread of ``pid`` (by OS thread name; equal names summed): [CPU time s, run-queue wait s, slices]
    from ``/proc/PID/task/TID/schedstat`` -- the wait is time the thread was runnable but had no CPU."""
    out: dict[str, list[float]] = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            name = Path(f"/proc/{pid}/task/{tid}/comm").read_text().strip()
            run_ns, wait_ns, slices = (int(x) for x in Path(f"/proc/{pid}/task/{tid}/schedstat").read_text().split())
        except (OSError, ValueError):
            continue
        acc = out.setdefault(name, [0.0, 0.0, 0.0])
        acc[0] += run_ns * 1e-9
        acc[1] += wait_ns * 1e-9
        acc[2] += slices
    return out


def schedstat_delta(before: dict, after: dict, seconds: float) -> dict:
    """Per thread: CPU share and run-queue wait share of ``seconds`` between two :func:`thread_schedstat`."""
    out = {}
    for name, (run1, wait1, n1) in after.items():
        run0, wait0, n0 = before.get(name, (0.0, 0.0, 0.0))
        out[name] = {"cpu_share": (run1 - run0) / seconds, "runqueue_wait_share": (wait1 - wait0) / seconds,
                     "slices": int(n1 - n0)}
    return out


# ------------------------------------------------------------------------------------------ frames
class TpdoClock(can.Listener):
    """Kernel receive timestamps of the frames with the given COB-IDs (TPDOs, and the own looped-back SYNC
    when ``SYNC_COB`` is among them)."""

    def __init__(self, cob_ids: list[int]):
        self.times: dict[int, list[float]] = {c: [] for c in cob_ids}

    def on_message_received(self, msg: can.Message) -> None:
        lst = self.times.get(msg.arbitration_id)
        if lst is not None:
            lst.append(msg.timestamp)

    def clear(self) -> None:
        for lst in self.times.values():
            lst.clear()


class SdoReply(can.Listener):
    """The latest SDO response of the given nodes."""

    def __init__(self, node_ids):
        self.cobs = {0x580 + n for n in node_ids}
        self.event = threading.Event()
        self.last = None

    def on_message_received(self, msg):
        if msg.arbitration_id in self.cobs:
            self.last = msg
            self.event.set()


def sdo(bus, reply: SdoReply, node_id: int, index: int, sub: int = 0, value: int | None = None, size: int = 4,
        timeout_s: float = 1.0) -> int:
    """Expedited SDO upload (``value`` None) or download; returns the uploaded value (unsigned)."""
    reply.event.clear()
    if value is None:
        data = bytes([0x40, index & 0xFF, index >> 8, sub, 0, 0, 0, 0])
    else:
        cmd = {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
        data = bytes([cmd, index & 0xFF, index >> 8, sub]) + int(value).to_bytes(4, "little", signed=value < 0)
    bus.send(can.Message(arbitration_id=0x600 + node_id, data=data, is_extended_id=False))
    if not reply.event.wait(timeout_s):
        raise RuntimeError(f"SDO timeout 0x{index:04X}:{sub}")
    if reply.last.data[0] == 0x80:
        raise RuntimeError(f"SDO abort 0x{int.from_bytes(reply.last.data[4:8], 'little'):08X} on 0x{index:04X}")
    return int.from_bytes(reply.last.data[4:8], "little")


def setup_csp(bus, reply: SdoReply, node_id: int, mode: int = 8) -> int:
    """Drive ``node_id`` into OPERATION ENABLED in ``mode`` (8 CSP) with RPDO2 (CW + target) synchronous and
    TPDO2 (SW + position) on every SYNC, the other TPDOs off; returns the position actual value [inc]."""
    sdo(bus, reply, node_id, 0x6060, value=mode, size=1)
    sdo(bus, reply, node_id, 0x6065, value=50_000)  # 50 mm following error window: never trips here
    sdo(bus, reply, node_id, 0x1401, 2, value=1, size=1)
    sdo(bus, reply, node_id, 0x1801, 2, value=1, size=1)
    for tpdo, base in ((0x1800, 0x180), (0x1802, 0x380), (0x1803, 0x480)):
        sdo(bus, reply, node_id, tpdo, 1, value=0x80000000 | (base + node_id))
    bus.send(can.Message(arbitration_id=0x000, data=bytes([0x01, node_id]), is_extended_id=False))
    for cw in (0x06, 0x07, 0x0F):
        sdo(bus, reply, node_id, 0x6040, value=cw, size=2)
    state = sdo(bus, reply, node_id, 0x6041) & 0x6F
    if state != 0x27:
        raise RuntimeError(f"node {node_id} not enabled (statusword & 0x6F = 0x{state:02X})")
    return int.from_bytes(sdo(bus, reply, node_id, 0x6064).to_bytes(4, "little"), "little", signed=True)


def sync_loop(bus, targets: dict[int, int | None], period_s: float, n_sync: int, *, spin_s: float = 3e-4,
              amplitude_inc: int = 20_000, sine_hz: float = 0.5, bar=None) -> np.ndarray:
    """Send per period a CSP target RPDO2 (``x0 + amplitude sin(2 pi f t)``) for each node of ``targets``
    (node id -> x0 [inc]; None: no RPDO, e.g. a spindle in PV) and then a SYNC; returns the user-space
    ``time.time()`` taken right before each SYNC's ``send`` [s].

    Pacing: ``time.sleep`` until ``spin_s`` before the deadline, then a spin (``spin_s`` = 0: sleep to the
    deadline; under SCHED_FIFO the kernel wakes the thread within some ten us, no spin needed). After a stall of
    this process longer than a period, the missed ticks are dropped, as a SYNC producer's timer does: no burst of
    catch-up SYNCs (which the drive would then have to work off, its late answers being this process' doing)."""
    sync_times = np.zeros(n_sync)
    sync_msg = can.Message(arbitration_id=SYNC_COB, data=b"", is_extended_id=False)
    perf = time.perf_counter
    t_next = perf() + 0.01
    two_pi_f_dt = 2 * np.pi * sine_hz * period_s
    for k in range(n_sync):
        while True:
            left = t_next - perf()
            if left <= 0:
                break
            time.sleep(left - spin_s if left > spin_s + 1e-4 else (0 if spin_s else left))
        s = np.sin(two_pi_f_dt * k)
        for nid, x0 in targets.items():
            if x0 is None:
                continue
            target = x0 + int(amplitude_inc * s)
            bus.send(can.Message(arbitration_id=0x300 + nid,
                                 data=(0x0F).to_bytes(2, "little") + target.to_bytes(4, "little", signed=True),
                                 is_extended_id=False))
        sync_times[k] = time.time()
        bus.send(sync_msg)
        t_next += period_s
        behind = perf() - t_next
        if behind > period_s:  # this process stalled: a SYNC producer keeps its tick, it does not send a burst
            t_next += (behind // period_s) * period_s
        if bar is not None and k % 1000 == 0:
            bar.update(1000 if k else 1)
    return sync_times


def pair(times: np.ndarray, sync_times: np.ndarray) -> np.ndarray:
    """Latency of each SYNC [s]: one TPDO per SYNC in order when the counts agree, else the first TPDO at or
    after each SYNC (an estimate; NaN when there is none)."""
    times = np.asarray(times)
    if len(times) == len(sync_times):
        return times - sync_times
    if not len(times):
        return np.full(len(sync_times), np.nan)
    idx = np.searchsorted(times, sync_times)
    lat = times[np.minimum(idx, len(times) - 1)] - sync_times
    lat[idx >= len(times)] = np.nan
    return lat


def latency_stats(times, sync_times: np.ndarray, period_s: float) -> dict:
    """SYNC -> TPDO statistics [us]: missed (SYNCs without a TPDO), late (after the next SYNC), p50/p99/max."""
    lat = pair(np.asarray(times), sync_times) * 1e6
    ok = lat[np.isfinite(lat)]
    return {
        "tpdos": int(len(times)),
        "missed_cycles": int(len(sync_times) - len(times)),  # SYNCs that got no TPDO at all
        "late_tpdos": int(np.count_nonzero(ok > period_s * 1e6)),  # arrived after the next SYNC
        "latency_us_p50": float(np.percentile(ok, 50)) if len(ok) else None,
        "latency_us_p99": float(np.percentile(ok, 99)) if len(ok) else None,
        "latency_us_p999": float(np.percentile(ok, 99.9)) if len(ok) else None,
        "latency_us_max": float(ok.max()) if len(ok) else None,
    }


def percentiles_us(x_s, qs=(50, 99, 99.9, 100)) -> dict:
    """Percentiles of seconds ``x_s`` in us (NaN dropped), keyed ``p50``, ``p99``, ``p99.9``, ``max``."""
    x = np.asarray(x_s, dtype=float) * 1e6
    x = x[np.isfinite(x)]
    if not len(x):
        return {}
    return {("max" if q == 100 else f"p{q:g}"): float(np.percentile(x, q)) for q in qs}
