"""The drive / axis options against the independent reference axis (``virtualaxis.refaxis``, written apart from the
kernel): for a reference case whose withheld effect is one of the options, our simulator runs every trace of the
case with the case's nominal config, and with the nominal config plus the option set to the case's TRUE value
(nothing fitted), and prints the RMS residual per channel (measured - simulated).

    python benchmarks/bench_plant_vocab_ref.py [--full] [--json out.json]

``--full``: the cases' full 100 mm strokes (default: the quick 10 mm cases of the test suite). Traces are
simulated after the reference's standstill pre-roll convention (0.5 s at the first command value, not compared).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from virtualaxis.config import load_axis_config
from virtualaxis.refaxis.cases import make_case
from virtualaxis.sim.batch import simulate_command

PREROLL_S = 0.5
CHANNELS = ("pos_meas", "pos_fb", "motor_pos", "force_drive")

#: case -> (option label, config changes with the case's true value)
CASES: dict[str, list[tuple[str, dict]]] = {
    "rigid_pp/viscous_asymmetry": [("viscous -v = 400 N s/m", {"friction": {"viscous_negative_n_s_per_m": 400.0}})],
    "rigid_pp/speed_estimator": [("two-sample speed estimate",
                                  {"control": {"speed_estimator": "two_sample_difference"}})],
    "two_mass/time_delay": [
        ("dead time 0.6 ms, position loop only", {"sensors": {"dead_time_s": 6e-4}}),
        ("dead time 0.6 ms on the feedback sensor", {"sensors": {"dead_time_s": 6e-4,
                                                                  "dead_time_scope": "feedback_sensor"}}),
    ],
    "rigid_pp/time_delay": [
        ("dead time 2.5 ms, position loop only", {"sensors": {"dead_time_s": 2.5e-3}}),
        ("dead time 2.5 ms on the feedback sensor", {"sensors": {"dead_time_s": 2.5e-3,
                                                                  "dead_time_scope": "feedback_sensor"}}),
    ],
}
#: the reference's drives derive the speed feed-forward from the set-point difference (a CSP drive): the two-mass
#: cases are also run with that form, alone and with the case's option
CSP_FF = {"control": {"velocity_ff_form": "setpoint_difference"}}
CASES["two_mass/clean"] = [("set-point difference feed-forward", CSP_FF)]
CASES["two_mass/time_delay"] += [
    ("set-point ff", CSP_FF),
    ("set-point ff + dead time, position loop only", {**CSP_FF, "sensors": {"dead_time_s": 6e-4}}),
    ("set-point ff + dead time on the feedback sensor",
     {**CSP_FF, "sensors": {"dead_time_s": 6e-4, "dead_time_scope": "feedback_sensor"}}),
]


def residual_rms(cfg, trace_path: Path) -> dict[str, float]:
    data = np.genfromtxt(trace_path, delimiter=",", names=True)
    cols = {n: data[n] for n in data.dtype.names}
    t = np.asarray(cols["t"], float)
    x = np.asarray(cols["pos_cmd"], float)
    dt = float(t[1] - t[0])
    n_pre = int(round(PREROLL_S / dt))
    tt = np.arange(n_pre + len(t)) * dt
    xx = np.concatenate([np.full(n_pre, x[0]), x])
    fext = None
    if "force_ext" in cols:
        fext = np.concatenate([np.zeros(n_pre), np.asarray(cols["force_ext"], float)])
    sim = simulate_command(cfg, tt, xx, fext, seed=0)
    out = {}
    for ch in CHANNELS:
        if ch in cols and ch in sim:
            r = np.asarray(cols[ch], float) - sim[ch][n_pre:]
            if ch == "motor_pos":
                r = r - np.mean(r[:50])  # the encoder's offset is not a gap (the diagnosis removes it too)
            out[ch] = float(np.sqrt(np.mean(r * r)))
    return out


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--full", action="store_true")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    res: dict = {}
    with tempfile.TemporaryDirectory() as d:
        for case, options in CASES.items():
            files = make_case(case, Path(d) / case.replace("/", "-"), seed=0, quick=not args.full)
            cfg = load_axis_config(files.config_path)
            traces = files.fit + files.holdout
            variants = [("nominal config", cfg)] + [(lab, cfg.replace(**ch)) for lab, ch in options]
            res[case] = {}
            print(f"{case}: {len(traces)} traces, RMS residual per channel (median over traces)")
            for lab, c in variants:
                per = [residual_rms(c, p) for p in traces]
                med = {ch: float(np.median([r[ch] for r in per if ch in r])) for ch in per[0]}
                res[case][lab] = {"median": med, "per_trace": per}
                txt = ", ".join(f"{ch} {v * 1e6:.3f} um" if ch != "force_drive" and ch != "motor_pos" else
                                (f"{ch} {v:.3f} N" if ch == "force_drive" else f"{ch} {v * 1e3:.4f} mrad")
                                for ch, v in med.items())
                print(f"  {lab:42s} {txt}")
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
