"""Cost of the drive / axis options (control/options.py) in the compiled kernel.

    python benchmarks/bench_plant_options.py [--reps N] [--json out.json]

Model: the every-effect seed-000 model of bench_plant.py (10 s of a 100 mm sine at F6000). Each option is switched
on alone, and all together, and timed against the model with every option at its default, measured in the same run,
interleaved (default, option, default, option, ...): CPU time of one thread, median of ``--reps``. A ratio of 1.00
means no cost. The defaults reproduce the kernel before the options bit for bit (docs/plant.md).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_plant import every_effect_config, sine  # noqa: E402

from virtualaxis.sim.simulator import AxisSimulator  # noqa: E402


def options(cfg) -> dict:
    opts = {
        "viscous asymmetry": {"friction": {"viscous_negative_n_s_per_m": 2.0 * cfg.friction.viscous_n_s_per_m + 50}},
        "two-sample speed estimate": {"control": {"speed_estimator": "two_sample_difference"}},
        "speed filter 0.5 ms": {"control": {"speed_filter_time_constant_s": 5e-4}},
        "dead time on the feedback sensor": {"sensors": {"dead_time_scope": "feedback_sensor"}},
    }
    opts["set-point difference feed-forward"] = {"control": {"velocity_ff_form": "setpoint_difference"}}
    every: dict = {}
    for ch in opts.values():
        for sec, kv in ch.items():
            every.setdefault(sec, {}).update(kv)
    opts["all options on"] = every
    return opts


def one_run(sim: AxisSimulator, p, v, a) -> float:
    sim.reset(0.0)
    sim.enable(True)
    c0 = time.process_time()
    sim.run_arrays(p, v, a, np.zeros(len(p)))
    return time.process_time() - c0


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--duration", type=float, default=10.0, help="simulated seconds per run")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    base_cfg = every_effect_config()
    t, p, v, a = sine(args.duration)
    base = AxisSimulator(base_cfg)
    one_run(base, p[:10], v[:10], a[:10])  # compile / load the cache
    res: dict = {"duration_s": args.duration, "reps": args.reps, "options": {}}
    for name, change in options(base_cfg).items():
        sim = AxisSimulator(base_cfg.replace(**change), discrete=base.dm)
        one_run(sim, p[:10], v[:10], a[:10])
        tb, to = [], []
        for _ in range(args.reps):
            tb.append(one_run(base, p, v, a))
            to.append(one_run(sim, p, v, a))
        mb, mo = statistics.median(tb), statistics.median(to)
        res["options"][name] = {"default_cpu_s": mb, "option_cpu_s": mo, "ratio": mo / mb,
                                "rtf_default": args.duration / mb, "rtf_option": args.duration / mo}
        print(f"{name:36s} default {args.duration / mb:5.0f}x  option {args.duration / mo:5.0f}x  "
              f"ratio {mo / mb:.3f}")
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
