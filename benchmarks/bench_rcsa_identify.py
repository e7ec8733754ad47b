"""Benchmark: three-position joint identification (seed 002 eqs. 25-26) and the FRF evaluation rate.

Runs the reference setting -- four modes, population 15 x 8 = 120, 200 generations, differential evolution
with ``workers=2, updating="deferred"`` -- on 'measured' FRFs generated from known joints plus noise at
l = 0.6, 1.0, 1.6 m, and prints wall time, objective evaluations, FRF evaluations per second, the
recovered stiffness errors and the held-out (0.8, 1.3, 1.9 m) natural-frequency errors. A serial
single-core FRF rate is printed as the same-run baseline.

    python benchmarks/bench_rcsa_identify.py [--noise-seeds 3,4,5] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from virtualaxis.config import load_axis_config
from virtualaxis.rcsa.identify import (
    Eq26Objective,
    frf_evaluations_per_objective,
    identify_joints,
    predict_modes,
    relative_errors,
)
from virtualaxis.rcsa.measured import modes_from_frfs, synthetic_frfs
from virtualaxis.rcsa.params import JointParams, rcsa_model_from_config

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "seed002-usst.toml"
TRUTH = JointParams(4.28e7, 2.94e7, 7.09e8, 5.53e3, 100.0, 100.0, 500.0, 0.1)
TRAIN, HELD_OUT = [0.6, 1.0, 1.6], [0.8, 1.3, 1.9]


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--noise-seeds", default="3,4,5")
    ap.add_argument("--generations", type=int, default=200)
    ap.add_argument("--population", type=int, default=15)
    ap.add_argument("--json", default="")
    ap.add_argument("--amplitude-weight", type=float, default=None, help="default: rcsa.identification")
    a = ap.parse_args()
    model = rcsa_model_from_config(load_axis_config(CONFIG))
    ident = model.identification
    freq = np.arange(5.0, 1000.0 + 1e-9, 0.1)
    weight = ident.amplitude_weight if a.amplitude_weight is None else a.amplitude_weight
    print(f"eq. 26 amplitude weight {weight:g}")
    print(f"machine: {os.cpu_count()} cores, {cpu_model()}; load average {os.getloadavg()}")
    runs = []
    for noise_seed in (int(s) for s in a.noise_seeds.split(",")):
        frfs = synthetic_frfs(
            model.with_joints(TRUTH),
            TRAIN + HELD_OUT,
            freq,
            magnitude_noise=0.01,
            phase_noise_deg=0.5,
            seed=noise_seed,
        )
        measured = modes_from_frfs(frfs, model)
        train, held = measured.select(TRAIN), measured.select(HELD_OUT)
        # same-run baseline: serial objective calls on one core
        objective = Eq26Objective(model, train, weight)
        x = np.log10(TRUTH.as_array())
        objective(x)
        n_serial = 300
        t0 = time.perf_counter()
        for _ in range(n_serial):
            objective(x)
        serial_s = (time.perf_counter() - t0) / n_serial
        frf_per_call = frf_evaluations_per_objective(model, train, TRUTH)
        with tqdm(total=a.generations, desc=f"noise seed {noise_seed}", unit="gen") as bar:
            res = identify_joints(
                model,
                train,
                lower=ident.lower,
                upper=ident.upper,
                population_per_parameter=a.population,
                generations=a.generations,
                seed=ident.seed,
                workers=2,
                amplitude_weight=weight,
                progress=lambda g: bar.update(1),
            )
        frf_evals = res.objective_evaluations * frf_per_call
        stiff_err = res.joints.as_array()[:4] / TRUTH.as_array()[:4] - 1.0
        held_err = [
            float(np.nanmax(relative_errors(p.natural_frequencies_hz, held.frequencies_hz[i])))
            for i, p in enumerate(predict_modes(model, HELD_OUT, res.joints))
        ]
        run = {
            "noise_seed": noise_seed,
            "amplitude_weight": weight,
            "population": a.population * 8,
            "generations": res.generations,
            "wall_time_s": res.wall_time_s,
            "objective_evaluations": res.objective_evaluations,
            "frf_evaluations": frf_evals,
            "frf_evaluations_per_s": frf_evals / res.wall_time_s,
            "serial_frf_evaluations_per_s": frf_per_call / serial_s,
            "objective": res.objective,
            "objective_at_truth": objective(x),
            "stiffness_relative_errors": {
                k: float(e) for k, e in zip(("k_al", "k_ar", "k_n", "k_m"), stiff_err, strict=True)
            },
            "held_out_max_frequency_error": dict(zip(map(str, HELD_OUT), held_err, strict=True)),
        }
        runs.append(run)
        print(
            f"noise seed {noise_seed}: wall {res.wall_time_s:.1f} s for {res.generations} generations x"
            f" {a.population * 8}; {res.objective_evaluations} objective calls = {frf_evals} FRF evaluations"
            f" -> {run['frf_evaluations_per_s']:.3g} FRF/s on 2 workers (serial baseline"
            f" {run['serial_frf_evaluations_per_s']:.3g} FRF/s, ratio"
            f" {run['frf_evaluations_per_s'] / run['serial_frf_evaluations_per_s']:.2f})"
        )
        print(
            "   stiffness errors: "
            + ", ".join(f"{k} {100 * v:+.1f} %" for k, v in run["stiffness_relative_errors"].items())
        )
        print(
            "   held-out max natural-frequency error: "
            + ", ".join(f"{k} m {100 * v:.2f} %" for k, v in run["held_out_max_frequency_error"].items())
        )
        print(f"   objective {res.objective:.4f} (at the true joints {run['objective_at_truth']:.4f})")
    if a.json:
        Path(a.json).write_text(
            json.dumps({"cpu": cpu_model(), "cores": os.cpu_count(), "runs": runs}, indent=1)
        )


if __name__ == "__main__":
    main()
