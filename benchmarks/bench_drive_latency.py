"""SYNC -> TPDO latency, missed cycles, SDO round trip and CPU share of the virtual CiA 402 drive.

The drive runs in its own process (``virtualaxis serve``, real-time pacing) on a host-local
``udp_multicast`` bus (hop_limit 0); this process is the master: it sends SYNC every period (plus a CSP
target per axis, a slow sine so that the plant works) and timestamps the synchronous TPDO of every axis
(TPDO2: statusword + position actual value; the other TPDOs are switched off, as a master would).

    python benchmarks/bench_drive_latency.py                      # 60 s per case: 1 ms / 500 us, 1 / 2 axes
    python benchmarks/bench_drive_latency.py --seconds 10 --cases 1ms:1
    python benchmarks/bench_drive_latency.py --rt-priority 20     # serve under SCHED_FIFO
    python benchmarks/bench_drive_latency.py --cases 1ms:7 --rt-priority 20 --cpu-latency-us 0   # + PM QoS
    python benchmarks/bench_drive_latency.py --cases 1ms:7 --lockstep   # six feed axes + the spindle, lockstep
    python benchmarks/bench_drive_latency.py --scale --seconds 10  # 1/2/4/7 axes x real time/lockstep x FIFO/not
    python benchmarks/bench_drive_latency.py --scale --seconds 8 --rounds 3   # the same, 3 interleaved rounds
    python benchmarks/bench_drive_latency.py --cycle-cost          # in-process cost per cycle and axis (1/2/4/7)
    python benchmarks/bench_drive_latency.py --cycle-cost --axes 1,3,7 --bytecodes   # the same as bytecodes
    python benchmarks/bench_drive_latency.py --cycle-cost --axes 3 --split   # where it goes, timed in place
    python benchmarks/bench_drive_latency.py --host-jitter --rt-priority 20   # the host's own tail (see below)
    python benchmarks/bench_drive_latency.py --host-stalls --rt-priority 20   # does the host slow all CPUs at once

With 7 axes the 7th is the spindle (``configs/spindle.toml``, profile velocity mode at 3000 rpm); the others
are feed axes in CSP. ``--bitrate`` passes the emulated CAN bit rate to ``serve`` (default 0 here: the raw
latency of the runtime; 1000000 adds the frame times of a 1 Mbit/s bus). With the emulation on, ``wire floor``
is the least SYNC -> TPDO time the emulated bus allows each node (:func:`wire_floor_us`): the master hands its
RPDOs and then the SYNC over at once, and on the wire they run one after the other (95 bits per RPDO2, 47 for the
SYNC, without stuff bits; the first of them counts as ended when it arrived); then the k-th node's TPDO2 waits for
the k - 1 with lower identifiers and takes its own 95 bits. At 1 Mbit/s the third of 3 axes cannot answer within
2 x 95 + 47 + 3 x 95 = 522 us of the SYNC's send, nor the seventh of 7 (six RPDOs: the spindle has none) within
5 x 95 + 47 + 7 x 95 = 1 187 us, however fast the drive.

Every plant effect of the config is switched on (backlash, friction, cogging and the [effects] section:
lead error, thermal growth, an extra resonance; sensor noise). Latency = the TPDO's kernel receive
timestamp in the master's socket (SO_TIMESTAMPNS) minus the master's ``time.time`` right before it sent the SYNC.
The master's own stalls are reported apart (``master_stalls``: SYNCs sent more than two periods after the previous
one, and the longest gap): after one, a burst of SYNCs follows that the drive must work off, and the late answers
that follow are the master's doing. A SYNC that gets no TPDO at all is a missed cycle; a TPDO that arrives after
the next SYNC is counted as late. ``cycles`` / ``overrun``: the drive's own count, read by SDO before and after
the SYNCs, of the drive cycles it ran (0x2110:5) and of those that started late or were given up (0x2110:2; in
lockstep, the cycles of SYNCs it answered but could not run). Writes a JSON beside the printed table only with
``--json FILE`` (the committed figures are ``benchmarks/bench_drive_latency.json``: name it to regenerate them).

``--host-jitter``: no drive at all. A fixed plain-Python workload (``_master.host_jitter``, ~100 us) back to back,
then once per 1 ms as a drive cycle runs; the p99 of the paced runs against the back-to-back p50 is how much the
host itself stretches a cycle (a shared virtual CPU: 5-15x at the 1 % level). The latency tails above cannot be
smaller than this host's; state it beside them as ``--cycle-cost``.

``--host-stalls``: no drive and no sleeping timed. The same workload back to back in one process per CPU; runs
slower than 3x their CPU's median are counted, grouped into bursts, and matched across the CPUs. When nearly every
slow run of one CPU has one on another within 2 ms, the host slows the whole virtual machine at once (a hypervisor
sharing or descheduling its CPUs): no priority, pinning or idle setting inside the machine removes that tail.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import can
import numpy as np
from tqdm import tqdm

REPO = Path(__file__).resolve().parents[1]
if not os.environ.get("PYTHONPATH"):  # this checkout, unless PYTHONPATH names one (A/B against another src)
    sys.path.insert(0, str(REPO / "src"))

import virtualaxis  # noqa: E402
from virtualaxis.config import load_axis_config  # noqa: E402

sys.path.insert(0, str(REPO / "benchmarks"))
from _master import (  # noqa: E402
    CLI,
    SdoReply,
    TpdoClock,
    _cpu_model,
    cpu_seconds,
    host_jitter,
    host_stalls,
    latency_stats,
    sdo,
    setup_csp,
    sync_loop,
)

#: the src folder the package was imported from: `serve` runs from the same one
SRC = str(Path(virtualaxis.__file__).resolve().parents[1])


def all_effects_config(path: Path) -> Path:
    cfg = load_axis_config(REPO / "configs" / "seed000-hust.toml")
    cfg = cfg.replace(
        effects={
            "lead_error_ppm": 20.0,
            "lead_error_periodic_m": 2e-6,
            "thermal_expansion_per_k": 11.5e-6,
            "thermal_resistance_k_per_w": 0.05,
            "thermal_time_constant_s": 600.0,
            "resonance_frequency_hz": 180.0,
            "resonance_mass_kg": 20.0,
        },
        sensors={"position_noise_m": 2e-8, "current_noise_a": 0.01},
    )
    path.write_text(cfg.to_toml(header="bench_drive_latency: seed000-hust with every plant effect on"))
    return path


SPINDLE = REPO / "configs" / "spindle.toml"
SPINDLE_RPM = 3000.0


def run_case(period_s: float, n_axes: int, seconds: float, config: Path, port: int, rt_priority: int,
             lockstep: bool = False, bitrate: int = 0, cpu_latency_us: int | None = None,
             serve_args: list[str] | None = None, src: str = SRC) -> dict:
    spec = f"udp_multicast:239.74.163.2,port={port}"
    args = [*CLI, "serve", "--can", spec, "--status-interval", "0", "--duration", str(seconds + 60)]
    if bitrate is not None:  # (None: a checkout older than the CAN bit-rate emulation, which it does not know)
        args += ["--bitrate", str(bitrate)]
    spindle = n_axes == 7
    for nid in range(1, n_axes + 1):
        cfg = SPINDLE if spindle and nid == 7 else config
        args += ["--axis", f"A{nid}={nid}:{cfg}"]
    if rt_priority:
        args += ["--rt-priority", str(rt_priority)]
    if lockstep:
        args += ["--lockstep"]
    if cpu_latency_us is not None:
        args += ["--cpu-latency-us", str(cpu_latency_us)]
    args += serve_args or []
    proc = subprocess.Popen(
        args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": src},
    )
    line = proc.stdout.readline()
    if not line.startswith("ready:"):
        proc.kill()
        raise RuntimeError(f"serve did not start: {line} {proc.stderr.read()}")
    bus = can.Bus(interface="udp_multicast", channel="239.74.163.2", port=port, hop_limit=0)
    node_ids = list(range(1, n_axes + 1))
    tpdo_cobs = [0x280 + n for n in node_ids]
    clock = TpdoClock(tpdo_cobs)
    reply = SdoReply(node_ids)
    notifier = can.Notifier(bus, [clock, reply], timeout=0.05)
    try:
        # SDO round trip: expedited upload of the statusword
        rtts = []
        for _ in range(500):
            t0 = time.perf_counter()
            sdo(bus, reply, 1, 0x6041)
            rtts.append(time.perf_counter() - t0)
        x0: dict[int, int] = {}
        for nid in node_ids:
            if lockstep:
                sdo(bus, reply, nid, 0x1006, value=int(round(period_s * 1e6)))  # one drive cycle per SYNC
            is_spindle = spindle and nid == 7
            # RPDO2 (CW + target) synchronous, TPDO2 (SW + position) on every SYNC, enabled; spindle: profile velocity
            x0[nid] = setup_csp(bus, reply, nid, mode=3 if is_spindle else 8)
            if is_spindle:  # 0x60FF in position units per second: 1/3600 rev per unit
                sdo(bus, reply, nid, 0x60FF, value=int(SPINDLE_RPM / 60 * 3600))
        for lst in clock.times.values():
            lst.clear()
        # the drives' own count of cycles run (0x2110:5) and of cycles started late or given up (0x2110:2)
        counts0 = {nid: _drive_counts(bus, reply, nid) for nid in node_ids}
        n_sync = int(seconds / period_s)
        cpu0, wall0 = cpu_seconds(proc.pid), time.perf_counter()
        with tqdm(
            total=n_sync, desc=f"SYNC {period_s * 1e6:.0f} us, {n_axes} axis", unit="sync", mininterval=1, leave=False
        ) as bar:  # target for the next cycle: 20 mm sine at 0.5 Hz, then SYNC
            # under SCHED_FIFO the master sleeps to each SYNC (woken within some ten us); a spin there would eat the
            # kernel's real-time budget that it shares with serve (RT throttling: stalls of ~100 ms)
            sync_times = sync_loop(bus, x0, period_s, n_sync, spin_s=0.0 if rt_priority else 3e-4, bar=bar)
        time.sleep(0.2)
        cpu1, wall1 = cpu_seconds(proc.pid), time.perf_counter()
        counts1 = {nid: _drive_counts(bus, reply, nid) for nid in node_ids}
        result = {
            "sync_period_us": period_s * 1e6,
            "axes": n_axes,
            "lockstep": lockstep,
            "rt_priority": rt_priority,
            "bitrate": bitrate,
            "cpu_latency_us": cpu_latency_us,
            "serve_args": serve_args or [],
            "seconds": seconds,
            "syncs": n_sync,
            "serve_cpu_share_of_one_core": (cpu1 - cpu0) / (wall1 - wall0),
        }
        for k_th, (nid, cob) in enumerate(zip(node_ids, tpdo_cobs, strict=True), start=1):
            result[f"node{nid}"] = {k: v for k, v in latency_stats(clock.times[cob], sync_times, period_s).items()
                                    if k != "latency_us_p999"}
            result[f"node{nid}"]["wire_floor_us"] = wire_floor_us(
                k_th, bitrate, sum(1 for x in x0.values() if x is not None))
            for k, key in enumerate(("drive_cycles", "drive_overruns")):
                a, b = counts0[nid][k], counts1[nid][k]
                result[f"node{nid}"][key] = None if a is None or b is None else (b - a) & 0xFFFFFFFF
        result["sdo_rtt_us_p50"] = float(np.percentile(rtts, 50) * 1e6)
        # the master's own stalls: SYNCs sent more than 2 periods after the previous one (then a burst follows
        # that the drive must work off: its late answers are the master's doing, not the drive's)
        gaps = np.diff(sync_times)
        result["master_stalls"] = int(np.sum(gaps > 2 * period_s))
        result["master_max_sync_gap_ms"] = float(gaps.max() * 1e3) if len(gaps) else 0.0
        result["sdo_rtt_us_p99"] = float(np.percentile(rtts, 99) * 1e6)
    finally:
        notifier.stop()
        bus.shutdown()
        proc.terminate()
        out, _ = proc.communicate(timeout=20)
    result["serve_report"] = out.strip().splitlines()[-1] if out.strip() else ""
    lat = [result[f"node{n}"] for n in node_ids]
    overruns = [x["drive_overruns"] for x in lat]  # (None: a checkout without 0x2110)
    result["all_axes"] = {
        "latency_us_p50_max": max(x["latency_us_p50"] or 0 for x in lat),
        "latency_us_p99_max": max(x["latency_us_p99"] or 0 for x in lat),
        "latency_us_max": max(x["latency_us_max"] or 0 for x in lat),
        "missed_cycles": sum(x["missed_cycles"] for x in lat),
        "late_tpdos": sum(x["late_tpdos"] for x in lat),
        "drive_overruns": None if None in overruns else sum(overruns),
        "master_stalls": result["master_stalls"],
        "master_max_sync_gap_ms": result["master_max_sync_gap_ms"],
    }
    return result


#: bits of a classical CAN frame with 6 data bytes (TPDO2: statusword + position) without stuff bits: SOF,
#: identifier, RTR, IDE, r0, DLC, 48 data bits, CRC-15, CRC delimiter, ACK slot + delimiter, EOF, intermission
TPDO2_MIN_BITS = 1 + 11 + 3 + 4 + 48 + 15 + 1 + 2 + 7 + 3


#: bits of a SYNC frame (no data) without stuff bits
SYNC_MIN_BITS = TPDO2_MIN_BITS - 48


def wire_floor_us(k_th: int, bitrate: int | None, rpdos_ahead: int = 0) -> float:
    """The least time from the master's SYNC send to the ``k_th`` node's TPDO2 that the emulated bus allows [us]:
    the ``rpdos_ahead`` RPDO2 frames (6 data bytes, as TPDO2) the master handed over just before the SYNC and the
    SYNC itself run on the wire first, one after the other; the first of them counts as ended when it arrived (the
    emulation cannot tell a master that emulates its side, and hands a frame over at its end, from one that does
    not). Then, every node's TPDO being ready at once, arbitration sends them lowest identifier first, so the k-th
    waits for k - 1 others and takes its own frame time. Stuff bits not counted: a lower bound. 0 without the
    emulation."""
    if not bitrate:
        return 0.0
    ahead = (rpdos_ahead - 1) * TPDO2_MIN_BITS + SYNC_MIN_BITS if rpdos_ahead else 0
    return 1e6 * (ahead + k_th * TPDO2_MIN_BITS) / bitrate


def _drive_counts(bus, reply: SdoReply, nid: int) -> tuple[int | None, int | None]:
    """The drive's own (cycles run 0x2110:5, cycles started late 0x2110:2); None where the drive has no such
    object (a checkout older than it)."""
    out = []
    for sub in (5, 2):
        try:
            out.append(sdo(bus, reply, nid, 0x2110, sub))
        except RuntimeError:
            out.append(None)
    return out[0], out[1]


def code_ab(args) -> int:
    """``--code NAME=DIR`` (repeated): every case of ``--cases`` once per checkout ``DIR`` (``serve`` from
    ``DIR/src``, the axis ``DIR/configs/seed000-hust.toml`` as that checkout ships it, ``--bitrate`` only where that
    ``serve`` knows it), interleaved within each of ``--rounds`` rounds so that a drifting machine load hits every
    version alike; a bisection of the latency over the history in one run. Per case and version: the median over
    the rounds of the worst axis' figures."""
    codes = []
    for item in args.code:
        name, _, root = item.partition("=")
        root_p = Path(root).resolve()
        serve_py = root_p / "src" / "virtualaxis" / "cli" / "serve.py"
        if not name or not serve_py.is_file():
            raise SystemExit(f"--code {item}: expected NAME=DIR with DIR a checkout (no {serve_py})")
        knows_bitrate = '"--bitrate"' in serve_py.read_text()
        codes.append((name, str(root_p / "src"), root_p / "configs" / "seed000-hust.toml", knows_bitrate))
    cases = _parse_cases(args.cases)
    runs = [(r, case, code) for r in range(args.rounds) for case in cases for code in codes]
    rows: dict[tuple, list[dict]] = {}
    for i, (rnd, (period_s, n_axes), (name, src, config, knows_bitrate)) in enumerate(
            tqdm(runs, desc="versions x cases", unit="run")):
        try:
            res = run_case(period_s, n_axes, args.seconds, config, 45000 + os.getpid() % 500 + i % 400,
                           args.rt_priority, args.lockstep, args.bitrate if knows_bitrate else None,
                           args.cpu_latency_us, args.serve_args, src=src)
        except RuntimeError as exc:  # (a version that cannot run the case: reported, the others go on)
            print(f"{name} {period_s * 1e3:g} ms x {n_axes}: {exc}", file=sys.stderr)
            continue
        res.update(code=name, round=rnd)
        rows.setdefault((period_s, n_axes, name), []).append(res)
    machine = _machine()
    print(f"\nmachine: {machine['nproc']} cores, {machine['cpu']}, load average {machine['load_average_at_end']}")
    print(f"{'SYNC':>7} {'axes':>4} {'version':<12} {'p50 us':>8} {'p99 us':>8} {'max us':>9} {'missed':>7} "
          f"{'late':>6} {'overruns':>8} {'CPU':>6} {'rounds':>6}")
    summary = []
    for (period_s, n_axes), (name, *_) in ((c, v) for c in cases for v in codes):
        got = rows.get((period_s, n_axes, name), [])
        if not got:
            continue
        worst = [r["all_axes"] for r in got]
        med = {k: float(np.median([w[k] for w in worst if w[k] is not None]))
               if any(w[k] is not None for w in worst) else None
               for k in ("latency_us_p50_max", "latency_us_p99_max", "latency_us_max", "missed_cycles", "late_tpdos",
                         "drive_overruns")}
        med["cpu_percent"] = float(np.median([100 * r["serve_cpu_share_of_one_core"] for r in got]))
        summary.append({"sync_period_us": period_s * 1e6, "axes": n_axes, "code": name, "rounds": len(got), **med})
        ovr = "-" if med["drive_overruns"] is None else f"{med['drive_overruns']:.0f}"
        print(f"{period_s * 1e6:>5.0f}us {n_axes:>4} {name:<12} {med['latency_us_p50_max']:>8.0f} "
              f"{med['latency_us_p99_max']:>8.0f} {med['latency_us_max']:>9.0f} {med['missed_cycles']:>7.0f} "
              f"{med['late_tpdos']:>6.0f} {ovr:>8} {med['cpu_percent']:>5.0f}% {len(got):>6}")
    if args.json:
        Path(args.json).write_text(json.dumps({"machine": machine, "args": vars(args), "summary": summary,
                                               "runs": [r for v in rows.values() for r in v]}, indent=2))
        print(f"wrote {args.json}")
    return 0


def _parse_cases(text: str) -> list[tuple[float, int]]:
    cases = []
    for item in text.split(","):
        period, axes = item.split(":")
        period_s = float(period[:-2]) * 1e-3 if period.endswith("ms") else float(period[:-2]) * 1e-6
        cases.append((period_s, int(axes)))
    return cases


def cycle_cost(axis_counts=(1, 2, 4, 7), cycles: int = 2000, repeats: int = 3) -> list[dict]:
    """In-process cost of one communication cycle of the runtime (lockstep, 1 ms SYNC, a synchronous RPDO2
    per axis): SYNC + RPDO handled, every drive stepped, TPDO2 packed and sent on a ``virtual`` bus with no
    other listener. Best of ``repeats`` runs of ``cycles`` cycles [us], wall time and this thread's CPU time (the
    CPU time is what a loaded machine disturbs least). The start-up heap is frozen as ``serve`` does."""
    from virtualaxis.canopen_slave import NmtState
    from virtualaxis.runtime import AxisNode, Runtime

    feed = load_axis_config(REPO / "configs" / "seed000-hust.toml")
    spindle = load_axis_config(SPINDLE)
    out = []
    for n in axis_counts:
        bus = can.Bus(interface="virtual", channel=f"bench-cycle-{os.getpid()}-{n}")
        axes = [AxisNode(bus, i + 1, spindle if (n == 7 and i == 6) else feed, name=f"A{i + 1}") for i in range(n)]
        rt = Runtime(bus, axes, lockstep=True)
        try:  # as `serve` does (older checkouts have no such step)
            from virtualaxis.runtime.pacing import freeze_startup_heap
        except ImportError:
            pass
        else:
            freeze_startup_heap()
        for ax in axes:
            ax.slave.boot(0.0)
            ax.app.flush()
            ax.slave.write(0x1401, 2, 1)
            ax.slave.write(0x1006, 0, 1000)
            ax.slave._set_state(NmtState.OPERATIONAL)
            ax.slave.sdo_download(0x6060, 0, bytes([3 if (n == 7 and ax.node_id == 7) else 8]))
            for cw in (6, 7, 15):
                ax.slave.sdo_download(0x6040, 0, cw.to_bytes(2, "little"))
        sync = can.Message(arbitration_id=0x80, data=b"", is_extended_id=False)

        def one(k: int, axes=axes, sync=sync, rt=rt) -> None:
            stamp = time.time()
            for ax in axes:
                ax.slave.receive(can.Message(arbitration_id=0x300 + ax.node_id, is_extended_id=False,
                                             data=b"\x0f\x00" + (k * 5).to_bytes(4, "little", signed=True),
                                             timestamp=stamp))
                sync.timestamp = stamp
                ax.slave.receive(sync)
            rt.poll_once()

        for k in range(300):
            one(k)
        best = best_cpu = float("inf")
        for r in range(repeats):
            t, c = time.perf_counter(), time.thread_time()
            for k in range(cycles):
                one(300 + r * cycles + k)
            best = min(best, (time.perf_counter() - t) / cycles)
            best_cpu = min(best_cpu, (time.thread_time() - c) / cycles)
        if rt.stats.drive_exceptions:
            raise RuntimeError(rt.stats.last_exception)
        out.append({"axes": n, "cycle_us": best * 1e6, "per_axis_us": best * 1e6 / n,
                    "cycle_cpu_us": best_cpu * 1e6, "per_axis_cpu_us": best_cpu * 1e6 / n})
        bus.shutdown()
    return out


def cycle_bytecodes(axis_counts=(1, 3, 7), cycles: int = 100) -> list[dict]:
    """Python bytecodes the runtime executes per axis in one communication cycle of :func:`cycle_cost` (frame
    handling, drive cycles, TPDOs; median of ``cycles`` cycles after its warm-up): a count that a loaded machine
    does not disturb (the compiled plant kernel and C functions count nothing; their share is the same in any
    checkout of the same plant)."""
    from virtualaxis.runtime import pacing

    counts: list[int] = []
    n_ops = [0]

    def local(frame, event, arg):
        if event == "opcode":
            n_ops[0] += 1
        return local

    def tracer(frame, event, arg):
        frame.f_trace_opcodes = True
        frame.f_trace_lines = False
        return local

    poll_once = pacing.Runtime.poll_once

    def traced(self) -> None:
        n_ops[0] = 0
        sys.settrace(tracer)
        try:
            poll_once(self)
        finally:
            sys.settrace(None)
        counts.append(n_ops[0])

    out = []
    pacing.Runtime.poll_once = traced
    try:
        for n in axis_counts:
            counts.clear()
            cycle_cost((n,), cycles=cycles, repeats=1)
            timed = sorted(counts[300:])  # (cycle_cost's 300 warm-up cycles left out)
            out.append({"axes": n, "bytecodes_per_axis": timed[len(timed) // 2] / n})
    finally:
        pacing.Runtime.poll_once = poll_once
    return out


#: the parts of a communication cycle that --split times in place: (class path, public method, label)
SPLIT_PARTS = (
    ("virtualaxis.canopen_slave.slave.CanopenSlave", "receive", "frames received (RPDO, SYNC) into the slave"),
    ("virtualaxis.canopen_slave.slave.CanopenSlave", "poll", "slave poll (queued frames, timers)"),
    ("virtualaxis.canopen_slave.slave.CanopenSlave", "transmit_sync", "SYNC answer: TPDO packed and sent"),
    ("virtualaxis.canopen_slave.slave.CanopenSlave", "apply_sync", "RPDO applied to the drive"),
    ("virtualaxis.drive.core.Drive", "step", "drive cycle (modes, plant, monitors, outputs)"),
    ("virtualaxis.drive.canopen_app.Cia402Application", "flush", "OD mirror flushes"),
)
#: parts inside one of :data:`SPLIT_PARTS`, timed the same way and shown under it (not added to the sum)
SPLIT_NESTED = (
    ("virtualaxis.sim.simulator.AxisSimulator", "advance", "of the drive cycle: the compiled plant (advance)"),
)


def cycle_split(axes: int = 3, cycles: int = 3000) -> dict:
    """Where one communication cycle's CPU goes, per axis: :func:`cycle_cost`'s cycle with each part of
    :data:`SPLIT_PARTS` timed in place (wall time around each call, in a loop of one thread; the parts do not
    nest, except that the RPDO's application flushes the mirror too). In place, not in isolation: the same part
    run alone in a loop costs a fraction (caches stay warm), so only this says what a cut of a part would buy."""
    import importlib

    from virtualaxis.runtime import pacing

    spent: dict[str, float] = {label: 0.0 for *_, label in SPLIT_PARTS + SPLIT_NESTED}
    total = [0.0]
    originals = []
    tt = time.perf_counter  # (wall time of this one thread: a CPU-time clock is a system call, 1-2 us per read here)

    def timed(fn, label):
        def wrapper(*a, **k):
            t0 = tt()
            try:
                return fn(*a, **k)
            finally:
                spent[label] += tt() - t0
        return wrapper

    for path, name, label in SPLIT_PARTS + SPLIT_NESTED:
        mod, _, cls_name = path.rpartition(".")
        cls = getattr(importlib.import_module(mod), cls_name)
        originals.append((cls, name, getattr(cls, name), label))
    poll_once = pacing.Runtime.poll_once
    try:
        for cls, name, fn, label in originals:
            setattr(cls, name, timed(fn, label))

        def whole(self) -> None:
            t0 = tt()
            try:
                poll_once(self)
            finally:
                total[0] += tt() - t0
        pacing.Runtime.poll_once = whole
        cycle_cost((axes,), cycles=cycles, repeats=1)
    finally:
        for cls, name, fn, _label in originals:
            setattr(cls, name, fn)
        pacing.Runtime.poll_once = poll_once
    n = (300 + cycles) * axes  # (cycle_cost's warm-up cycles included)
    nested = {label for *_, label in SPLIT_NESTED}
    parts = {label: 1e6 * v / n for label, v in spent.items() if label not in nested}
    inner = {label: 1e6 * v / n for label, v in spent.items() if label in nested}
    return {"axes": axes, "cycles": cycles, "per_axis_cycle_us": 1e6 * total[0] / n, "parts_us": parts,
            "nested_us": inner}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--cases", default="1ms:1,1ms:2,500us:1,500us:2", help="period:axes,...")
    ap.add_argument("--rt-priority", type=int, default=0)
    ap.add_argument("--json", default=None,
                    help="results file, written only when given (the committed figures are "
                         "benchmarks/bench_drive_latency.json: name it to regenerate them)")
    ap.add_argument("--lockstep", action="store_true", help="serve --lockstep (0x1006 = the SYNC period)")
    ap.add_argument("--bitrate", type=int, default=0, help="serve --bitrate (0: no CAN timing emulation)")
    ap.add_argument("--scale", action="store_true",
                    help="1ms with 1/2/4/7 axes, real time and lockstep, with and without SCHED_FIFO")
    ap.add_argument("--cpu-latency-us", type=int, default=None,
                    help="serve --cpu-latency-us (PM QoS CPU wake-up bound; default: not requested)")
    ap.add_argument("--serve-arg", dest="serve_args", action="append", default=[],
                    help="one more argument for serve (repeat), e.g. --serve-arg=--sync-spin-us --serve-arg=150")
    ap.add_argument("--rounds", type=int, default=1,
                    help="--scale / --code: repeat the interleaved case list N times")
    ap.add_argument("--code", action="append", default=[], metavar="NAME=DIR",
                    help="run the cases once per checkout DIR (repeat; interleaved; see code_ab)")
    ap.add_argument("--cycle-cost", action="store_true", help="only the in-process cost per cycle and axis")
    ap.add_argument("--host-jitter", action="store_true",
                    help="only the host's stretch of a fixed plain-Python workload paced at 1 ms (_master.host_jitter;"
                         " with --rt-priority N at SCHED_FIFO N)")
    ap.add_argument("--host-stalls", action="store_true",
                    help="only whether the host slows all CPUs at once (_master.host_stalls; --seconds, default 5)")
    ap.add_argument("--axes", default="1,2,4,7", help="--cycle-cost: the axis counts, comma-separated")
    ap.add_argument("--bytecodes", action="store_true",
                    help="--cycle-cost as Python bytecodes per axis and cycle (load-independent)")
    ap.add_argument("--split", action="store_true",
                    help="--cycle-cost split into its parts, timed in place (first of --axes; see cycle_split)")
    args = ap.parse_args()
    if args.cycle_cost and args.split:
        r = cycle_split(int(args.axes.split(",")[0]))
        print(f"{r['axes']} axes: {r['per_axis_cycle_us']:.1f} us per axis and communication cycle (timed; "
              "--cycle-cost without the timing is the reference)")
        for label, us in r["parts_us"].items():
            print(f"  {us:7.2f} us  {label}")
            if label.startswith("drive cycle"):
                for inner, inner_us in r["nested_us"].items():
                    print(f"      {inner_us:7.2f} us  {inner}")
        print(f"  {r['per_axis_cycle_us'] - sum(r['parts_us'].values()):7.2f} us  the rest: the runtime's loop and "
              "the timing's own cost (the mirror flushes inside the RPDO's application counted twice)")
        if args.json:
            Path(args.json).write_text(json.dumps({"machine": _machine(), "cycle_split": r}, indent=2))
        return 0
    if args.cycle_cost and args.bytecodes:
        for r in cycle_bytecodes(tuple(int(n) for n in args.axes.split(","))):
            print(f"{r['axes']:>4} axes: {r['bytecodes_per_axis']:.0f} Python bytecodes per axis and cycle")
        return 0
    if args.host_jitter:
        res = host_jitter(rt_priority=args.rt_priority)
        print(f"plain Python workload [us]: back to back p50 {res['work_us_p50_back_to_back']:.1f} / p99 "
              f"{res['work_us_p99_back_to_back']:.1f}; paced at 1 ms p50 {res['work_us_p50_paced']:.1f} / p99 "
              f"{res['work_us_p99_paced']:.1f} / max {res['work_us_max_paced']:.0f} (p99 = "
              f"{res['paced_p99_over_p50']:.1f}x the back-to-back p50); wake-up late p99 "
              f"{res['wake_late_us_p99']:.0f} / max {res['wake_late_us_max']:.0f}")
        if args.json:
            Path(args.json).write_text(json.dumps({"machine": _machine(), "host_jitter": res}, indent=2))
        return 0
    if args.host_stalls:
        res = host_stalls(seconds=5.0 if args.seconds == 60.0 else args.seconds, rt_priority=args.rt_priority)
        for c in res["cpus"]:
            print(f"CPU {c['cpu']}: {c['runs']} runs, p50 {c['work_us_p50']:.0f} / p99 {c['work_us_p99']:.0f} / max "
                  f"{c['work_us_max']:.0f} us, {c['slow_runs']} slower than 3x p50")
        print(f"slow runs of CPU {res['cpus'][0]['cpu']} that another CPU saw within 2 ms: "
              f"{res['slow_runs_seen_by_another_cpu']}")
        for bu in res["bursts"]:
            print(f"  burst at {bu['at_s']:6.2f} s: {bu['length_ms']:5.1f} ms, {bu['slow_runs']} slow runs, "
                  f"{bu['speed_kept'] * 100:.0f} % of the speed kept")
        print(f"time in bursts: {res['time_in_bursts'] * 100:.2f} % of {res['seconds']:.1f} s")
        if args.json:
            Path(args.json).write_text(json.dumps({"machine": _machine(), "host_stalls": res}, indent=2))
        return 0
    if args.cycle_cost:
        res = cycle_cost(tuple(int(n) for n in args.axes.split(",")))
        base = res[0]["cycle_us"]
        print(f"{'axes':>4} {'cycle us':>9} {'per axis us':>11} {'vs 1 axis':>9} {'CPU us':>8} {'CPU/axis':>8}")
        for r in res:
            print(f"{r['axes']:>4} {r['cycle_us']:>9.1f} {r['per_axis_us']:>11.1f} {r['cycle_us'] / base:>8.2f}x "
                  f"{r['cycle_cpu_us']:>8.1f} {r['per_axis_cpu_us']:>8.1f}")
        if args.json:  # (not over the committed latency figures by default: a different measurement)
            Path(args.json).write_text(json.dumps({"machine": _machine(), "cycle_cost": res}, indent=2))
            print(f"wrote {args.json}")
        return 0
    if args.scale:
        return scale(args)
    if args.rt_priority:  # the master too, so that its SYNC timing is not the bottleneck
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.rt_priority))
    if args.code:
        return code_ab(args)
    cases = _parse_cases(args.cases)
    with tempfile.TemporaryDirectory() as tmp:
        config = all_effects_config(Path(tmp) / "all-effects.toml")
        results = []
        for i, (period_s, n_axes) in enumerate(cases):
            results.append(
                run_case(period_s, n_axes, args.seconds, config, 45000 + os.getpid() % 500 + i, args.rt_priority,
                         args.lockstep, args.bitrate, args.cpu_latency_us, args.serve_args)
            )
    machine = _machine()
    print(f"\nmachine: {machine['nproc']} cores, {machine['cpu']}, load average {machine['load_average_at_end']}")
    print(
        f"{'SYNC':>7} {'axes':>4} {'node':>4} {'p50 us':>8} {'p99 us':>8} {'max us':>9} {'missed':>7} {'late':>6} "
        f"{'cycles':>7} {'overrun':>7} {'SDO p50 us':>10} {'CPU':>6} {'master gap ms':>13} {'wire floor us':>13}"
    )
    for r in results:
        for nid in range(1, r["axes"] + 1):
            n = r[f"node{nid}"]
            print(
                f"{r['sync_period_us']:>5.0f}us {r['axes']:>4} {nid:>4} {n['latency_us_p50']:>8.0f} "
                f"{n['latency_us_p99']:>8.0f} {n['latency_us_max']:>9.0f} {n['missed_cycles']:>7} {n['late_tpdos']:>6} "
                f"{n.get('drive_cycles', -1):>7} {n.get('drive_overruns', -1):>7} {r['sdo_rtt_us_p50']:>10.0f} "
                f"{r['serve_cpu_share_of_one_core'] * 100:>5.0f}% "
                f"{r['master_max_sync_gap_ms']:>13.2f} {n.get('wire_floor_us', 0.0):>13.0f}"
            )
    if args.json:  # (only when asked: a profiling or trial run must not replace the committed figures)
        Path(args.json).write_text(json.dumps({"machine": machine, "args": vars(args), "results": results},
                                              indent=2))
        print(f"wrote {args.json}")
    return 0


def _machine() -> dict:
    return {
        "nproc": os.cpu_count(),
        "cpu": _cpu_model(),
        "python": platform.python_version(),
        "load_average_at_end": os.getloadavg(),
    }


def scale(args) -> int:
    """1 ms SYNC, 1/2/4/7 axes (7 = six feed axes + the spindle), real-time pacing and lockstep, with and
    without SCHED_FIFO (tried; reported when not permitted). ``--rounds`` repeats the whole case list, the
    cases interleaved within each round, so that a drifting machine load hits real time and lockstep alike.
    One line per case and round (the worst axis), then the median over the rounds."""
    fifo_ok = True
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(20))
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (AttributeError, PermissionError, OSError) as exc:
        fifo_ok = False
        print(f"SCHED_FIFO not permitted here ({exc}): only the cases without it run")
    results = []
    cases = [(n, lock, prio) for prio in ((0, 20) if fifo_ok else (0,)) for n in (1, 2, 4, 7) for lock in (False, True)]
    runs = [(r, case) for r in range(args.rounds) for case in cases]
    with tempfile.TemporaryDirectory() as tmp:
        config = all_effects_config(Path(tmp) / "all-effects.toml")
        for i, (rnd, (n, lock, prio)) in enumerate(tqdm(runs, desc="scale cases", unit="case")):
            if prio:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
            else:
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
            res = run_case(1e-3, n, args.seconds, config, 45000 + os.getpid() % 500 + i % 400, prio, lock,
                           args.bitrate, args.cpu_latency_us, args.serve_args)
            res["round"] = rnd
            res["load_average_at_end"] = os.getloadavg()
            results.append(res)
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    machine = _machine()
    print(f"\nmachine: {machine['nproc']} cores, {machine['cpu']}, load average {machine['load_average_at_end']}")
    head = (f"{'FIFO':>4} {'pacing':>9} {'axes':>4} {'round':>5} {'p50 us':>7} {'p99 us':>7} {'max us':>8} "
            f"{'missed':>6} {'late':>6} {'CPU':>5} {'mstall':>6}  (worst axis; mstall: master SYNC gaps > 2 periods)")
    print(head)

    def line(r, rnd) -> str:
        a = r["all_axes"]
        return (f"{'yes' if r['rt_priority'] else 'no':>4} {'lockstep' if r['lockstep'] else 'real time':>9} "
                f"{r['axes']:>4} {rnd:>5} {a['latency_us_p50_max']:>7.0f} {a['latency_us_p99_max']:>7.0f} "
                f"{a['latency_us_max']:>8.0f} {a['missed_cycles']:>6} {a['late_tpdos']:>6} "
                f"{r['serve_cpu_share_of_one_core'] * 100:>4.0f}% {a.get('master_stalls', 0):>6}")

    for r in results:
        print(line(r, str(r["round"])))
    summary = []
    if args.rounds > 1:
        print("\nmedian over the rounds (missed, late: summed)")
        print(head)
        for n, lock, prio in cases:
            rs = [r for r in results if (r["axes"], r["lockstep"], r["rt_priority"]) == (n, lock, prio)]
            agg = {k: float(np.median([r["all_axes"][k] for r in rs]))
                   for k in ("latency_us_p50_max", "latency_us_p99_max", "latency_us_max")}
            agg["missed_cycles"] = sum(r["all_axes"]["missed_cycles"] for r in rs)
            agg["late_tpdos"] = sum(r["all_axes"]["late_tpdos"] for r in rs)
            agg["master_stalls"] = sum(r["all_axes"]["master_stalls"] for r in rs)
            med = {"axes": n, "lockstep": lock, "rt_priority": prio, "all_axes": agg,
                   "serve_cpu_share_of_one_core": float(np.median([r["serve_cpu_share_of_one_core"] for r in rs]))}
            summary.append(med)
            print(line(med, "med"))
    if args.json:
        Path(args.json).write_text(json.dumps({"machine": machine, "args": vars(args), "fifo_permitted": fifo_ok,
                                               "results": results, "median_over_rounds": summary}, indent=2))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
