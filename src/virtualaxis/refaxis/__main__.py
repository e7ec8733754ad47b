"""``python -m virtualaxis.refaxis --out DIR [--quick] [--seed N] [--cases a,b] [--plot] [--list]``: write cases.

Each case goes to DIR/<structure>__<case>/ (config.toml, fit_*.csv, heldout_*.csv, truth.json, with --plot also
traces.png); the time per case is printed and DIR/timing.json holds it.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from virtualaxis.refaxis.cases import case_names, make_case


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m virtualaxis.refaxis", description=__doc__)
    ap.add_argument("--out", type=Path, help="output folder")
    ap.add_argument("--quick", action="store_true", help="10 mm stroke, three held-out traces")
    ap.add_argument("--seed", type=int, default=0, help="sensor-noise seed")
    ap.add_argument("--cases", default="", help="comma-separated case names (default: all)")
    ap.add_argument("--plot", action="store_true", help="also write traces.png per case (matplotlib)")
    ap.add_argument("--list", action="store_true", help="list the case names and exit")
    a = ap.parse_args(argv)
    names = case_names()
    if a.list:
        print("\n".join(names))
        return 0
    if a.out is None:
        print("error: --out DIR is required (or --list)", file=sys.stderr)
        return 2
    chosen = [c for c in a.cases.split(",") if c] or names
    unknown = [c for c in chosen if c not in names]
    if unknown:
        print(f"error: --cases: unknown case(s) {', '.join(unknown)}; see --list", file=sys.stderr)
        return 2
    timing: dict[str, float] = {}
    t_all = time.perf_counter()
    for i, name in enumerate(chosen, 1):
        t0 = time.perf_counter()
        cf = make_case(name, a.out / name.replace("/", "__"), seed=a.seed, quick=a.quick)
        timing[name] = time.perf_counter() - t0
        if a.plot:
            from virtualaxis.refaxis.plot import plot_case

            plot_case(cf.config_path.parent, cf.fit + cf.holdout, f"{name}: {cf.truth['notes']}")
        print(f"[{i}/{len(chosen)}] {name}: {timing[name]:.2f} s, {len(cf.fit)} fit + {len(cf.holdout)} held-out"
              f" traces, truth {cf.truth['effects'] or 'clean'}", flush=True)
    total = time.perf_counter() - t_all
    print(f"{len(chosen)} cases in {total:.1f} s ({total / len(chosen):.2f} s per case; the first includes numba"
          " compilation when the cache is cold)")
    (a.out / "timing.json").write_text(json.dumps({"per_case_s": timing, "total_s": total}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
