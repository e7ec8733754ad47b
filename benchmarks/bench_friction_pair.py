"""Coulomb and viscous friction together, from a mass-only nominal: does `virtualaxis diagnose` name both?

Traces of the independent reference axis (``virtualaxis.refaxis``, rigid P/P structure: force and position at the
load, both loops at 1 kHz) at the scale of a published lab ball-screw positioning axis: ~100 kg, Coulomb ~20 N,
viscous ~200 N s/m (the viscous force worth about the Coulomb force at the top speed), speeds to 0.15 m/s. The
config states the mass and the controller and no friction. The CLI runs in a subprocess; the script prints the
found vs true values per case and the held-out RMSE before -> after.

    python benchmarks/bench_friction_pair.py [--out DIR] [--cases a,b] [--seed N] [--jobs N]

Cases (truth; the config has none of it): ``pair`` Coulomb 20 N + viscous 200 N s/m on 100 kg; ``pair_heavy``
Coulomb 30 N + viscous 150 N s/m on 120 kg; ``coulomb`` Coulomb 20 N alone; ``viscous`` viscous 200 N s/m alone.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from virtualaxis.refaxis import cases as C
from virtualaxis.refaxis import commands as K

CASES: dict[str, dict] = {
    "pair": {"table_mass_kg": 100.0, "coulomb_n": 20.0, "viscous_n_s_per_m": 200.0},
    "pair_heavy": {"table_mass_kg": 120.0, "coulomb_n": 30.0, "viscous_n_s_per_m": 150.0},
    "coulomb": {"table_mass_kg": 100.0, "coulomb_n": 20.0, "viscous_n_s_per_m": 0.0},
    "viscous": {"table_mass_kg": 100.0, "coulomb_n": 0.0, "viscous_n_s_per_m": 200.0},
}
STROKE_M = 0.1


def commands() -> tuple[list, list]:
    """A positioning axis' moves: fit on moves at 50 and 150 mm/s and a sine with peak speed 150 mm/s; held out: a
    move at 100 mm/s and a sine at 75 mm/s (commands of the reference's own generator, 1 kHz)."""
    s = STROKE_M
    fit = [("ptp_slow", K.point_to_point(-0.4 * s, 0.4 * s, 0.05, 1.0, 20.0)),
           ("ptp_fast", K.point_to_point(-0.4 * s, 0.4 * s, 0.15, 1.5, 40.0)),
           ("sine_F9000", K.sine(9000, s, 1))]
    hold = [("ptp_mid", K.point_to_point(0.3 * s, -0.4 * s, 0.1, 1.0, 30.0)),
            ("sine_F4500", K.sine(4500, s, 1))]
    return fit, hold


def make(name: str, out: Path, seed: int) -> C.CaseFiles:
    truth = dict(CASES[name])
    truth.update(coulomb_negative_n=truth["coulomb_n"], viscous_negative_n_s_per_m=truth["viscous_n_s_per_m"])
    config = {"table_mass_kg": truth["table_mass_kg"], "coulomb_n": 0.0, "coulomb_negative_n": 0.0,
              "viscous_n_s_per_m": 0.0, "viscous_negative_n_s_per_m": 0.0}
    fit, hold = commands()
    return C.write_axis_case(out, "rigid_pp", truth, config, fit, hold, seed=seed, name=f"friction-{name}")


def found_values(report: dict) -> dict[str, float]:
    out: dict[str, float] = {}
    for e in report["effects"]:
        if e["accepted"]:
            for k in ("coulomb_n", "viscous_n_s_per_m"):
                if k in e["params"]:
                    out[k] = e["params"][k]["value"]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="", help="folder for traces and reports (default: a temporary one)")
    ap.add_argument("--cases", default="pair", help=f"comma-separated, of {', '.join(CASES)} (default: pair)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=2)
    a = ap.parse_args()
    names = [c for c in a.cases.split(",") if c]
    unknown = [c for c in names if c not in CASES]
    if unknown:
        print(f"error: --cases: unknown {', '.join(unknown)}", file=sys.stderr)
        return 2
    root = Path(a.out or tempfile.mkdtemp(prefix="friction_pair_"))
    env = dict(os.environ)
    for name in names:
        case = make(name, root / name, a.seed)
        t0 = time.perf_counter()
        cmd = [sys.executable, "-m", "virtualaxis.cli.main", "diagnose", "--config", str(case.config_path),
               *map(str, case.fit), "--holdout", *map(str, case.holdout), "--out", str(root / name / "out"),
               "--no-hybrid", "--jobs", str(a.jobs)]
        p = subprocess.run(cmd, capture_output=True, text=True, env=env)
        secs = time.perf_counter() - t0
        if p.returncode != 0:
            print(f"{name}: diagnose failed ({p.returncode}): {p.stderr.strip().splitlines()[-1:]}")
            continue
        rep = json.loads((root / name / "out" / "report.json").read_text())
        truth = CASES[name]
        found = found_values(rep)
        print(f"{name}: {rep['conclusion']}  ({secs:.0f} s)")
        for key, tv in (("coulomb_n", truth["coulomb_n"]), ("viscous_n_s_per_m", truth["viscous_n_s_per_m"])):
            fv = found.get(key)
            err = f"{100 * (fv - tv) / tv:+.1f} %" if fv is not None and tv else "-"
            print(f"  {key}: true {tv:g}, found {fv if fv is None else round(fv, 2)}  ({err})")
        fin = rep.get("final", {})
        for ch, m in (fin.get("heldout_rmse_ratio") or {}).items():
            print(f"  held-out {ch}: nominal / calibrated RMSE {m:.3g}")
    print(f"traces and reports in {root}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
