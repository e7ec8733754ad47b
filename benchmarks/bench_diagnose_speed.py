"""Speed of a full diagnosis: six 20 s traces at 1 kHz (sines F1000..F6000, 100 mm stroke) of the seed 000
ball-screw axis with a withheld backlash, the whole effect library, a local pool of --jobs workers.

Prints where the time goes (reading, baseline simulation, localisation, screening/refinement, verification,
hybrid models), the number of simulations and the cost of one 20 s simulation measured in the same run.

    python benchmarks/bench_diagnose_speed.py [--jobs 2] [--out /tmp/diag_speed]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from virtualaxis.diagnosis.bench import nominal_config
from virtualaxis.diagnosis.pipeline import run_diagnosis, write_outputs
from virtualaxis.diagnosis.trace import write_trace


def make_traces(out: Path) -> list[str]:
    from virtualaxis.sim import simulate_command

    nominal = nominal_config("ballscrew")
    truth = nominal.replace(backlash={"enabled": True, "gap_m": 20e-6})
    out.mkdir(parents=True, exist_ok=True)
    t = np.arange(20000) * 1e-3
    paths = []
    for k, f in enumerate((1000, 2000, 3000, 4000, 5000, 6000)):
        amp = 0.05
        w = f / 6e4 / amp
        pos = amp * (1 - np.cos(w * t))
        res = simulate_command(truth, t, pos, seed=k)
        p = out / f"sine_F{f}.csv"
        write_trace(p, {"t": t, "pos_cmd": pos, **{c: res[c] for c in ("pos_meas", "motor_pos", "vel_meas",
                                                                          "torque_meas", "current_q")}})
        paths.append(str(p))
    (out / "nominal.toml").write_text(nominal.to_toml("speed benchmark nominal"), encoding="utf-8")
    return paths


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", default="/tmp/diag_speed")
    a = ap.parse_args()
    out = Path(a.out)
    paths = make_traces(out / "traces")
    from virtualaxis.sim import simulate_command

    cfg = nominal_config("ballscrew")
    t = np.arange(20000) * 1e-3
    pos = 0.05 * (1 - np.cos(0.333 * t))
    simulate_command(cfg, t[:100], pos[:100])
    t0 = time.perf_counter()
    simulate_command(cfg.replace(friction={"coulomb_n": 41.0}), t, pos)
    one_sim = time.perf_counter() - t0
    t0 = time.perf_counter()
    result = run_diagnosis(cfg, paths, [], jobs=a.jobs)
    wall = time.perf_counter() - t0
    write_outputs(result, out / "diagnosis")
    rep = result.report
    tm = rep["timing"]
    print(f"six 20 s traces at 1 kHz, whole library ({len(rep['effects'])} applicable effects), jobs={a.jobs}")
    print(f"conclusion: {rep['conclusion']}")
    print(f"total wall time {wall:.1f} s")
    for k in ("read_s", "controller_check_s", "baseline_s", "localise_s", "fitting_s", "verify_s", "hybrid_s"):
        print(f"  {k:18s} {tm[k]:7.1f} s")
    print(f"  simulations of a 20 s trace (or shorter fit segments): {tm['simulations']}")
    print(f"  one 20 s simulation in this run: {one_sim:.2f} s "
          f"(fitting = {tm['fitting_s'] / one_sim:.0f} x one simulation)")
    scr = sum(e["seconds"] for e in rep["effects"] if e["stage"] == "screen")
    ref = sum(e["seconds"] for e in rep["effects"] if e["stage"] == "refine")
    print(f"  worker time: screening-only candidates {scr:.1f} s, refined candidates {ref:.1f} s")


if __name__ == "__main__":
    main()
