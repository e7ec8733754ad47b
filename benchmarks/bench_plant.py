"""Plant speed: real-time factor of the full seed-000 model, ratio against solve_ivp on the same equations,
cost vs simulated duration, peak memory while writing a trace, and start-up time with a warm compile cache.

    python benchmarks/bench_plant.py [--quick] [--json out.json]

Every figure is measured in this run; ratios use baselines measured in the same run. The machine is shared
and noisy: each timing is the median of several repetitions (CPU time of this process, one thread).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from plant_helpers import config_with  # noqa: E402

from virtualaxis.sim.reference import ReferenceAxis  # noqa: E402
from virtualaxis.sim.simulator import AxisSimulator  # noqa: E402


def every_effect_config():
    return config_with({
        "effects": {"lead_error_ppm": 20.0, "lead_error_periodic_m": 2e-6, "thermal_expansion_per_k": 11.5e-6,
                    "thermal_resistance_k_per_w": 0.5, "thermal_time_constant_s": 5.0},
        "sensors": {"dead_time_s": 125e-6, "position_noise_m": 5e-8, "current_noise_a": 0.005},
        "friction": {"coulomb_negative_n": 70.0},
    })


def sine(duration_s: float, cycle_s: float = 1e-3):
    amp, vmax = 0.05, 0.1
    w = vmax / amp
    t = np.arange(int(round(duration_s / cycle_s)) + 1) * cycle_s
    return t, amp * (1 - np.cos(w * t)), amp * w * np.sin(w * t), amp * w * w * np.cos(w * t)


def kernel_seconds(cfg, duration_s: float, reps: int) -> list[float]:
    t, p, v, a = sine(duration_s)
    sim = AxisSimulator(cfg)
    sim.enable(True)
    sim.run_arrays(p[:10], v[:10], a[:10], np.zeros(10))  # compile / load cache
    times = []
    for _ in range(reps):
        sim.reset(0.0)
        sim.enable(True)
        c0 = time.process_time()
        sim.run_arrays(p, v, a, np.zeros(len(t)))
        times.append(time.process_time() - c0)
    return times


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer repetitions, no 100 s run")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    reps = 3 if args.quick else 7
    cfg = every_effect_config()
    res: dict = {"machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
                             "python": platform.python_version()}}

    # 1. real-time factor of the full model
    k = kernel_seconds(cfg, 10.0, reps)
    rtf = 10.0 / statistics.median(k)
    res["rtf_full_model"] = {"simulated_s": 10.0, "median_cpu_s": statistics.median(k), "min_cpu_s": min(k),
                             "real_time_factor_median": rtf, "real_time_factor_best": 10.0 / min(k)}
    print(f"full seed-000 model, every effect on: real-time factor {rtf:.0f}x (median of {reps}), "
          f"best {10.0 / min(k):.0f}x")

    # 2. against solve_ivp on the same equations (same run); reference on a shorter span, per simulated second
    ref_cfg = cfg.replace(sensors={"position_noise_m": 0.0, "current_noise_a": 0.0})
    span = 0.1 if args.quick else 0.25
    t, p, v, a = sine(span)
    ref = ReferenceAxis(ref_cfg, rtol=1e-8, atol=1e-12)
    c0 = time.process_time()
    ref.run(t, p, v, a)
    ref_per_s = (time.process_time() - c0) / span
    kern = kernel_seconds(ref_cfg, span, reps)
    kern_per_s = statistics.median(kern) / span
    res["vs_solve_ivp"] = {"reference_cpu_s_per_simulated_s": ref_per_s, "kernel_cpu_s_per_simulated_s": kern_per_s,
                           "speed_ratio": ref_per_s / kern_per_s, "reference_span_s": span}
    print(f"solve_ivp reference: {ref_per_s:.1f} CPU s per simulated s; kernel {kern_per_s * 1e3:.2f} ms -> "
          f"{ref_per_s / kern_per_s:.0f}x faster")

    # 3. cost linear in simulated duration
    lin = {}
    for dur in ((1.0, 10.0) if args.quick else (1.0, 10.0, 100.0)):
        kk = kernel_seconds(cfg, dur, 3 if dur < 100 else 1)
        lin[str(dur)] = statistics.median(kk) / dur
        print(f"  {dur:>5.0f} s simulated: {lin[str(dur)] * 1e3:.2f} ms CPU per simulated second")
    res["cost_per_simulated_s"] = lin

    # 4. peak memory while writing a trace (separate processes, CLI path)
    mem = {}
    with tempfile.TemporaryDirectory() as d:
        cfg_path = Path(d) / "axis.toml"
        cfg_path.write_text(cfg.to_toml("benchmark config"))
        for dur in ((2.0, 20.0) if args.quick else (10.0, 100.0)):
            cmd = [sys.executable, "-c",
                   "import resource,sys; from virtualaxis.cli.main import main; rc = main(sys.argv[1:]); "
                   "print('MAXRSS', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)",
                   "simulate", "--config", str(cfg_path), "--profile", "sine:stroke_mm=100,feed_mm_min=6000",
                   "--duration", str(dur), "--out", str(Path(d) / "t.csv")]
            out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
            kb = int(out.split("MAXRSS")[1].split()[0])
            mem[str(dur)] = kb / 1024
            print(f"  peak RSS writing a {dur:g} s trace: {kb / 1024:.0f} MiB")
    res["peak_rss_mib_by_duration"] = mem

    # 5. start-up with a warm compile cache: import, load config, build, first step
    code = ("import time; t0=time.perf_counter(); from virtualaxis.config import load_axis_config; "
            "from virtualaxis.sim import AxisSimulator; c=load_axis_config('configs/seed000-hust.toml'); "
            "s=AxisSimulator(c); s.enable(True); s.advance(1); print('START', time.perf_counter()-t0)")
    starts = []
    for _ in range(reps):
        w0 = time.perf_counter()
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT).stdout
        starts.append((time.perf_counter() - w0, float(out.split("START")[1])))
    res["startup_s"] = {"process_wall_median": statistics.median(s[0] for s in starts),
                        "in_process_to_first_step_median": statistics.median(s[1] for s in starts)}
    print(f"start-up (warm cache): {res['startup_s']['process_wall_median']:.2f} s to the end of the first step "
          f"(process wall, median), {res['startup_s']['in_process_to_first_step_median']:.2f} s inside the process")

    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
