"""Sweep of the writable drive objects over their legal ranges: is the axis still stoppable?

    PYTHONPATH=src python3 benchmarks/bench_od_sweep.py [--stops quick,disable,fault] [--only 0x6085,0x6072]
                                                        [--json out.json]

For every writable object of the drive (eds/virtualaxis.eds; not the controlword 0x6040, the fault injection
0x2010 or a manufacturer alias), the values tried are the ends of its legal range (data type, EDS LowLimit /
HighLimit, the drive's own ranges, and either side of the per-axis loop-gain bounds of 0x2000 / 0x2003 /
0x2004: a value the drive refuses is counted, not run), its default and a few values in between (every value
of an option code). One value at a time, on the seed axis (configs/seed000-hust.toml) moving in PV at 200 mm/s
from -100 mm toward the + limit switch: the value is written, the drive runs 50 cycles, then one stop event:
quick stop (controlword 0x02, 0x605A as set), disable (0x06, 0x605B) or a fault
(0x4210 injected, 0x605E). Measured until the axis is at rest in the stop's final state:

- stop time [s] and distance [mm] from the event, peak table position against the + limit switch and the
  hard end stop;
- peak motor torque from the measured current (k_t |i_q|) against the torque limit in force at the event:
  min(0x6072 x 0x6076, 0x6073 x 0x6075 x k_t) and the power unit's limit (the config's current limit);
- the drive-cycle cost (``Drive.step(1)`` CPU time of the thread, so that other jobs on the host do not count):
  mean and worst over the run, and the write's own time.

A violation is: not at rest in the final state within 20 s (simulated) of the event, the table beyond the end
stop's surface, a peak torque above 1.05 x the limit + 1 per mille of rated torque, an exception in the drive
cycle, or a cycle or write costing more than 50 ms. The external force 0x2011 is swept too; beyond what the
motor holds (21 kN on the seed axis) no setting can stop the axis: those rows are listed apart ("beyond the
motor"), not as violations.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time

from virtualaxis.config import load_axis_config
from virtualaxis.drive import Drive
from virtualaxis.drive.core import ALIASES, DEFAULT_EDS, ObjectAccessError
from virtualaxis.drive.objects import DTYPE_RANGES, SPECS, eds_limits
from virtualaxis.runtime.axes import DEFAULT_CONFIG
from virtualaxis.sim.simulator import end_stops

SPEED_UNITS_S = 200_000  # 200 mm/s
START_M = -0.1
STOP_BOUND_S = 20.0
TORQUE_TOLERANCE = 1.05
TORQUE_RESOLUTION = 1e-3  # 1 per mille of rated torque: the resolution of 0x6077
SLOW_CYCLE_S = 0.05
SKIP = {(0x6040, 0), (0x2010, 0)} | set(ALIASES)
#: the states a stop ends in (a fault raised by the value itself, e.g. a following-error window of 0, ends it too)
FINAL = {"quick": ("SWITCH ON DISABLED", "QUICK STOP ACTIVE", "FAULT"), "disable": ("READY TO SWITCH ON", "FAULT"),
         "fault": ("FAULT",)}
#: profile objects: swept on a PP move (jerk-limited, 0x6086 = 3) instead of PV
PROFILE_KEYS = {(0x6081, 0), (0x6083, 0), (0x6084, 0), (0x6086, 0), (0x60A4, 1)}


def candidates(d: Drive, key: tuple[int, int]) -> list[float]:
    """Legal-range ends, default and a few interior values of one object (not yet checked by the drive)."""
    spec = SPECS[key]
    lo, hi = DTYPE_RANGES[spec.dtype]
    low, high = eds_limits(DEFAULT_EDS).get(key, (None, None))
    lo = lo if low is None else max(lo, low)
    hi = hi if high is None else min(hi, high)
    default = d.read_object(*key)
    if spec.dtype == "f32":
        vals = {0.0, float(default), float(default) / 10, float(default) * 10, 1e3, 1e6, -1e3, lo, hi}
        b = d.gain_bounds  # the drive's own per-axis bounds of the loop gains: the ends of what it accepts
        edge = {(0x2003, 0): b.speed_kp_max, (0x2000, 0): b.kv_max_1000_per_min,
                (0x2004, 0): b.speed_tn_min_s * 1000.0}.get(key)
        if edge is not None:
            vals |= {edge * (1 - 1e-6), edge * (1 + 1e-6)}
        return sorted(v for v in vals if lo <= v <= hi)
    lo, hi = int(lo), int(hi)
    if hi - lo <= 16:
        return list(range(lo, hi + 1))
    vals = {lo, lo + 1, hi, hi - 1, int(default), int(default) // 10, int(default) * 10, (lo + hi) // 2}
    for k in range(0, 10, 3):
        vals.add(10**k)
        vals.add(-(10**k))
    return sorted(v for v in vals if lo <= v <= hi)


def torque_limit_nm(d: Drive) -> float:
    """The torque the drive may apply now: 0x6072, 0x6073 as torque, the power unit's current limit [N m]."""
    cfg = d.cfg
    kt = d.simulator.torque_constant_nm_per_a
    rated_nm = d.read_object(0x6076) / 1e3
    rated_a = d.read_object(0x6075) / 1e3
    power_unit_a = cfg.control.current_limit_a if cfg.control.current_limit_a > 0 else 3 * cfg.motor.rated_current_a
    return min(d.read_object(0x6072) / 1e3 * rated_nm, d.read_object(0x6073) / 1e3 * rated_a * kt, power_unit_a * kt)


def run_case(d: Drive, key: tuple[int, int] | None, value, stop: str) -> dict:
    cfg = d.cfg
    kt = d.simulator.torque_constant_nm_per_a
    d.simulator.reset(START_M)
    d.power_on_reset()
    d.write_object(0x6083, 0, 2_000_000)
    pp = key in PROFILE_KEYS
    d.write_object(0x6060, 0, 1 if pp else 3)
    for cw in (6, 7, 0xF):
        d.set_controlword(cw)
    row: dict = {"object": None if key is None else f"0x{key[0]:04X}:{key[1]}", "value": value, "stop": stop,
                 "mode": "PP" if pp else "PV"}
    t_w = time.thread_time()
    if pp:  # the value first, then a jerk-limited move at 200 mm/s toward the + switch
        d.write_object(0x6086, 0, 3)
        d.write_object(0x6081, 0, SPEED_UNITS_S)
        try:
            d.write_object(key[0], key[1], value)
        except ObjectAccessError as exc:
            row["write"] = f"abort 0x{exc.code:08X}"
        d.write_object(0x607A, 0, int(0.25 / 1e-6))
        try:
            d.set_controlword(0x1F)
        except ObjectAccessError as exc:
            row["set_point"] = f"abort 0x{exc.code:08X}"
        row["write_ms"] = (time.thread_time() - t_w) * 1e3
    else:
        d.write_object(0x60FF, 0, SPEED_UNITS_S)
    for _ in range(1000):
        d.step(1)
        if d.state.velocity_actual_m_s >= 0.98 * SPEED_UNITS_S * 1e-6:
            break
    if not pp:
        t_w = time.thread_time()
        if key is not None:
            try:
                d.write_object(key[0], key[1], value)
            except ObjectAccessError as exc:
                row["write"] = f"abort 0x{exc.code:08X}"
        row["write_ms"] = (time.thread_time() - t_w) * 1e3
    cycle_max = cycle_sum = 0.0
    n = 0
    for _ in range(50):
        t = time.thread_time()
        d.step(1)
        dt = time.thread_time() - t
        cycle_max, cycle_sum, n = max(cycle_max, dt), cycle_sum + dt, n + 1
    s = d.state
    x0, v0, t0 = s.table_position_m, s.velocity_actual_m_s, s.time_s
    limit = torque_limit_nm(d)
    if stop == "quick":
        d.set_controlword(0x02)
    elif stop == "disable":
        d.set_controlword(0x06)
    else:
        d.inject_fault(0x4210)
    peak_nm = peak_x = 0.0
    stopped_at = None
    max_cycles = int(STOP_BOUND_S / d.cycle_s) + 1000
    for _ in range(max_cycles):
        t = time.thread_time()
        d.step(1)
        dt = time.thread_time() - t
        cycle_max, cycle_sum, n = max(cycle_max, dt), cycle_sum + dt, n + 1
        s = d.state
        peak_nm = max(peak_nm, abs(s.current_a) * kt)
        peak_x = max(peak_x, s.table_position_m)
        at_rest = abs(s.velocity_actual_m_s) < 1e-4 and s.cia402_state in FINAL[stop]
        if at_rest:  # (the end of the stop: what an external force does to the disabled axis after is not)
            stopped_at = s.time_s
            break
    switch_m = cfg.axis.stroke_m / 2 - d.settings.limit_switch_inset_m
    end_m = end_stops(cfg)[1]
    row.update(
        v0_mm_s=v0 * 1e3, stop_s=None if stopped_at is None else stopped_at - t0,
        distance_mm=(s.table_position_m - x0) * 1e3, past_switch_mm=(peak_x - switch_m) * 1e3,
        into_end_stop_mm=max(0.0, peak_x - end_m) * 1e3, peak_torque_nm=peak_nm, torque_limit_nm=limit,
        state=s.cia402_state, faults=[f"0x{f.emcy_code:04X}" for f in d.faults][:3],
        cycle_mean_us=cycle_sum / n * 1e6, cycle_max_us=cycle_max * 1e6,
        exceptions=d.counters["cycle_exceptions"],
    )
    bad = []
    if stopped_at is None or row["stop_s"] > STOP_BOUND_S:
        bad.append("not stopped")
    if row["into_end_stop_mm"] > 0:
        bad.append("end stop")
    resolution_nm = TORQUE_RESOLUTION * cfg.motor.kt_nm_per_a * cfg.motor.rated_current_a
    if peak_nm > TORQUE_TOLERANCE * limit + resolution_nm:
        bad.append("torque")
    if row["exceptions"]:
        bad.append("exception")
    if cycle_max > SLOW_CYCLE_S or row["write_ms"] > SLOW_CYCLE_S * 1e3:
        bad.append("slow cycle")
    row["violations"] = bad
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--stops", default="quick,disable,fault")
    ap.add_argument("--only", default="", help="comma-separated indices (e.g. 0x6085,0x6072)")
    ap.add_argument("--json", default="")
    args = ap.parse_args()
    stops = args.stops.split(",")
    only = {int(x, 16) for x in args.only.split(",") if x}
    cfg = load_axis_config(DEFAULT_CONFIG)
    d = Drive(cfg)
    kt = d.simulator.torque_constant_nm_per_a
    motor_hold_n = 3 * cfg.motor.rated_current_a * kt * 2 * math.pi / cfg.mechanics.lead_m
    keys = [k for k, s in SPECS.items() if s.access != "ro" and k not in SKIP and (not only or k[0] in only)]
    rows, refused = [], 0
    t_start = time.perf_counter()
    baseline = [run_case(d, None, None, stop) for stop in stops]
    base_cycle_us = sum(r["cycle_mean_us"] for r in baseline) / len(baseline)
    for key in keys:
        print(f"0x{key[0]:04X}:{key[1]} ...", file=sys.stderr, flush=True)
        d.simulator.reset(START_M)
        d.power_on_reset()
        for value in candidates(d, key):
            try:
                d.check_object_write(key[0], key[1], value)
            except ObjectAccessError:
                refused += 1
                continue
            for stop in stops:
                row = run_case(d, key, value, stop)
                if key == (0x2011, 0) and abs(value) > motor_hold_n:  # (0x2011 stays set through the stop)
                    row["beyond_motor"] = True
                    row["violations"] = []
                elif key == (0x2011, 0) and value and row["peak_torque_nm"] == 0.0:
                    row["coast_under_load"] = True  # pulses off at once (0x605B = 0): only a brake holds a load
                    row["violations"] = []
                rows.append(row)
    wall_s = time.perf_counter() - t_start
    bad = [r for r in rows if r["violations"]]
    print(f"host: {platform.processor() or platform.machine()}, python {platform.python_version()}; "
          f"baseline (defaults) drive cycle {base_cycle_us:.0f} us mean")
    print(f"{len(keys)} objects, {len(rows)} runs ({refused} values refused by the drive), {wall_s:.0f} s wall")
    worst = max(rows, key=lambda r: r["stop_s"] if r["stop_s"] is not None else math.inf)
    print(f"longest stop: {worst['object']} = {worst['value']} ({worst['stop']}): {worst['stop_s']} s, "
          f"{worst['distance_mm']:.1f} mm")
    far = max(rows, key=lambda r: r["past_switch_mm"])
    print(f"furthest: {far['object']} = {far['value']} ({far['stop']}): {far['past_switch_mm']:.1f} mm past the "
          f"+ switch ({far['into_end_stop_mm']:.1f} mm into the end stop)")
    ratio = max(rows, key=lambda r: r["peak_torque_nm"] / max(r["torque_limit_nm"], 1e-9))
    print(f"peak torque / limit: {ratio['object']} = {ratio['value']} ({ratio['stop']}): "
          f"{ratio['peak_torque_nm']:.3g} / {ratio['torque_limit_nm']:.3g} N m")
    slow = max(rows, key=lambda r: r["cycle_max_us"])
    print(f"worst cycle: {slow['object']} = {slow['value']} ({slow['stop']}): {slow['cycle_max_us']:.0f} us "
          f"({slow['cycle_max_us'] / base_cycle_us:.1f}x the baseline mean); mean over all runs "
          f"{sum(r['cycle_mean_us'] for r in rows) / len(rows) / base_cycle_us:.2f}x")
    n_beyond = sum(1 for r in rows if r.get("beyond_motor"))
    n_coast = sum(1 for r in rows if r.get("coast_under_load"))
    print(f"beyond the motor (0x2011 > {motor_hold_n / 1e3:.1f} kN): {n_beyond} runs; coasting (pulses off, no "
          f"torque) under 0x2011: {n_coast} runs; not counted")
    print(f"violations: {len(bad)}")
    for r in bad:
        stop_s = "-" if r["stop_s"] is None else f"{r['stop_s']:.2f}"
        print(f"  {r['object']} = {r['value']} ({r['stop']}): {', '.join(r['violations'])}; stop {stop_s} s, "
              f"{r['distance_mm']:.1f} mm, past switch {r['past_switch_mm']:.1f} mm, torque "
              f"{r['peak_torque_nm']:.3g}/{r['torque_limit_nm']:.3g} N m, cycle max {r['cycle_max_us']:.0f} us, "
              f"{r['state']} {r['faults']}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"baseline": baseline, "rows": rows, "refused": refused, "wall_s": wall_s}, f, indent=1)


if __name__ == "__main__":
    main()
