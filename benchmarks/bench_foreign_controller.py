"""Diagnosis of traces run by another controller than the config's (figures for docs/diagnosis.md).

The traces come from the small simulator in ``tests/test_diagnosis_controller.py`` (written independently of
virtualaxis: rigid 80 kg slide under a P/P cascade, force recorded at 1 kHz). Four scenarios, each diagnosed with
``run_diagnosis`` on F1500 + F4000 (fit) and F2500 (held out), 4 s each:

1. P/P Kv 25, Kp 5000, 8 kHz velocity loop; config: the P/PI example axis (Kv 40, Kp 8000, Ti 20 ms) — clean
2. the same with Coulomb friction 90 N (config 40 N)
3. P/P Kv 25, Kp 5000 with the velocity loop at 1 kHz; config: those gains at 125 us — clean
4. the same with Coulomb friction 90 N
5. P/P Kv 40, Kp 8000 with the velocity loop at 1 kHz; config: those gains at 125 us — clean

For each: the controller check's verdicts, the conclusion, and held-out RMSE before -> after; scenarios 1-4 again
with the controller check switched off, for comparison.

    python benchmarks/bench_foreign_controller.py [--out DIR]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from test_diagnosis_controller import RIGID, pp_cascade_trace  # noqa: E402

from virtualaxis.config import load_axis_config  # noqa: E402
from virtualaxis.diagnosis import pipeline  # noqa: E402
from virtualaxis.diagnosis.trace import write_trace  # noqa: E402


def scenarios():
    rigid = load_axis_config(RIGID)
    right_gains_fast_loop = rigid.replace(control={"velocity_kp_n_s_per_m": 5000.0, "speed_ti_s": 0.0,
                                                   "kv_per_s": 25.0})
    stiff = rigid.replace(control={"speed_ti_s": 0.0})  # the example's Kv 40, Kp 8000 as a P/P cascade
    return [
        ("P/P vs P/PI config, clean", rigid, {"coulomb": 40.0, "n_vel": 10}),
        ("P/P vs P/PI config, Coulomb 90 N", rigid, {"coulomb": 90.0, "n_vel": 10}),
        ("1 kHz speed loop vs 125 us config, clean", right_gains_fast_loop, {"coulomb": 40.0, "n_vel": 80}),
        ("1 kHz speed loop vs 125 us config, Coulomb 90 N", right_gains_fast_loop, {"coulomb": 90.0, "n_vel": 80}),
        ("Kv 40 / Kp 8000, 1 kHz speed loop vs 125 us config, clean", stiff, {"kv": 40.0, "kp": 8000.0, "n_vel": 80}),
    ]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="")
    a = ap.parse_args()
    out = Path(a.out or tempfile.mkdtemp(prefix="foreign_ctrl_"))
    check = pipeline.check_controllers
    for k, (title, cfg, kw) in enumerate(scenarios()):
        paths = []
        for j, feed in enumerate((1500.0, 4000.0, 2500.0)):
            p = out / f"s{k}" / f"F{int(feed)}.csv"
            p.parent.mkdir(parents=True, exist_ok=True)
            write_trace(p, pp_cascade_trace(feed, 4.0, seed=j, **kw))
            paths.append(str(p))
        for with_check in (True, False):
            pipeline.check_controllers = check if with_check else (lambda *args, **kwargs: [])
            t0 = time.perf_counter()
            rep = pipeline.run_diagnosis(cfg, paths[:2], paths[2:], jobs=1, hybrid=False).report
            dt = time.perf_counter() - t0
            before, after = rep["baseline_heldout"], rep["final"]["heldout"]
            shr = ", ".join(f"{ch} {before[ch]['rmse']:.4g} -> {after[ch]['rmse']:.4g}" for ch in sorted(after))
            found = ", ".join(e["name"] + " " + ", ".join(f"{n}={v['value']:.4g}" for n, v in e["params"].items())
                              for e in rep["effects"] if e["accepted"]) or "no significant effect"
            state = "on" if with_check else "off"
            print(f"{title} | controller check {state} | {found} | held out: {shr} | {dt:.0f} s")
            for c in rep.get("controller_check", []):
                g = c["identified_gains"]
                print(f"    {c['trace']}: {c['used']}, unexplained config {c['unexplained_config']:.3g} / identified "
                      f"{c['unexplained_identified']:.3g}, identified Kv {g['kv_per_s']:.4g} Kp {g['kp']:.5g} "
                      f"Ti {g['ti_s']:.3g} speed loop {g['speed_loop']}, overrides {c['overrides'] or '-'}")
    pipeline.check_controllers = check
    print(f"traces in {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
