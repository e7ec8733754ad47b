"""Stopping behaviour of the CiA 402 drive (reactions, limit switches, runaway), measured on the seed axis
through the Drive API (no bus; the same cases run through a real master in tests/test_cia402_field.py).

    PYTHONPATH=src python3 benchmarks/bench_fault_reactions.py [--json out.json]

Prints one line per case: travel after the event [mm], the final state, the faults. Runs against older
versions of the drive too (objects they lack are skipped), which is how the "before" figures in docs/drive.md
were taken.
"""

from __future__ import annotations

import argparse
import json
import math

from virtualaxis.config import load_axis_config
from virtualaxis.drive import Drive
from virtualaxis.runtime.axes import DEFAULT_CONFIG


def _drive(mode: int, **objects: float) -> Drive:
    d = Drive(load_axis_config(DEFAULT_CONFIG))
    for index, value in objects.items():
        try:
            d.write_object(int(index[1:5], 16), int(index[6:]) if len(index) > 5 else 0, value)
        except Exception:  # noqa: BLE001 - an object an older drive lacks
            pass
    d.write_object(0x6060, 0, mode)
    for cw in (6, 7, 0xF):
        d.set_controlword(cw)
    return d


def _faults(d: Drive) -> list[str]:
    return [f"0x{f.emcy_code:04X}" for f in d.faults][:3]


def csp_following_error() -> dict:
    """CSP at 183 mm/s, 0x605E = 2, 0x6085 = 10 m/s^2, following-error window tightened at full speed."""
    d = _drive(8, x605E=2, x6085=10_000_000)
    x = 0.0
    for i in range(2000):
        if d.state.cia402_state != "OPERATION ENABLED":
            break
        x += 183.0 * min(1.0, (i + 1) / 50)
        d.write_object(0x607A, 0, int(x))
        d.step(1)
        if i == 300:
            d.write_object(0x6065, 0, 100)
    s = d.state
    p0, v0 = s.position_actual_m, s.velocity_actual_m_s
    d.step(1500)
    s = d.state
    return {"case": "CSP FE fault, 0x605E=2, 0x6085=10 m/s^2", "v0_mm_s": v0 * 1e3,
            "ideal_mm": v0 * v0 / 20 * 1e3, "travel_mm": (s.position_actual_m - p0) * 1e3,
            "v_end_mm_s": s.velocity_actual_m_s * 1e3, "state": s.cia402_state, "faults": _faults(d)}


def pp_injected_fault() -> dict:
    """PP at 100 mm/s, injected 0x4210, 0x605E = 2, 0x6085 = 10 m/s^2."""
    d = _drive(1, x6081=100_000, x6083=2_000_000, x6085=10_000_000, x605E=2)
    d.write_object(0x607A, 0, 200_000)
    d.set_controlword(0x1F)
    d.step(300)
    p0 = d.state.position_actual_m
    d.inject_fault(0x4210)
    d.step(1000)
    s = d.state
    return {"case": "PP 100 mm/s, injected 0x4210", "ideal_mm": 0.1**2 / 20 * 1e3,
            "travel_mm": (s.position_actual_m - p0) * 1e3, "state": s.cia402_state, "faults": _faults(d)}


def pv_to_pp() -> dict:
    """PV at 100 mm/s, then 0x6060 = 1 (0x6084 = 2 m/s^2)."""
    d = _drive(3, x6083=2_000_000, x6084=2_000_000)
    d.write_object(0x60FF, 0, 100_000)
    d.step(400)
    p0 = pmax = d.state.position_actual_m
    d.write_object(0x6060, 0, 1)
    tmin = 0.0
    for _ in range(600):
        d.step(1)
        s = d.state
        tmin, pmax = min(tmin, s.torque_nm), max(pmax, s.position_actual_m)
    rated = d.read_object(0x6076, 0) / 1000.0
    return {"case": "PV 100 mm/s -> PP", "ideal_mm": 0.1**2 / 4 * 1e3, "travel_mm": (pmax - p0) * 1e3,
            "back_travel_mm": (pmax - s.position_actual_m) * 1e3, "min_torque_percent": tmin / rated * 100,
            "state": s.cia402_state, "faults": _faults(d)}


def toward_the_end(mode: int, label: str, setup) -> dict:
    d = _drive(mode, x607D_1=-2_000_000, x607D_2=2_000_000)
    setup(d)
    xmax = -math.inf
    for _ in range(3000):
        d.step(1)
        xmax = max(xmax, d.state.table_position_m)
    s = d.state
    return {"case": label, "stroke_end_m": d.cfg.axis.stroke_m / 2, "max_table_m": xmax,
            "state": s.cia402_state, "faults": _faults(d)}


def external_force() -> dict:
    d = Drive(load_axis_config(DEFAULT_CONFIG))
    d.write_object(0x2011, 0, -1e6)
    d.step(1000)
    x_disabled = d.state.table_position_m
    for cw in (6, 7, 0xF):
        d.set_controlword(cw)
    d.step(500)
    return {"case": "0x2011 = -1e6 N disabled 1 s, then enabled 0.5 s", "table_disabled_m": x_disabled,
            "table_enabled_m": d.state.table_position_m, "state": d.state.cia402_state,
            "cycle_exceptions": d.counters.get("cycle_exceptions", 0), "faults": _faults(d)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the results to this JSON file")
    args = ap.parse_args()
    cases = [
        ("CSP FE fault", csp_following_error),
        ("PP injected 0x4210", pp_injected_fault),
        ("PV -> PP", pv_to_pp),
        ("PP past the end", lambda: toward_the_end(1, "PP to 0.5 m (0x607D widened), 200 mm/s", lambda d: (
            d.write_object(0x6081, 0, 200_000), d.write_object(0x607A, 0, 500_000), d.set_controlword(0x1F)))),
        ("PV past the end", lambda: toward_the_end(3, "PV 200 mm/s toward +end (0x607D widened)",
                                                   lambda d: d.write_object(0x60FF, 0, 200_000))),
        ("PT past the end", lambda: toward_the_end(4, "PT 300 per mille toward +end",
                                                   lambda d: d.write_object(0x6071, 0, 300))),
        ("external force", external_force),
    ]
    results = []
    for name, case in cases:
        try:
            results.append(case())
        except Exception as exc:  # noqa: BLE001 - an older drive dying is a result too
            results.append({"case": name, "exception": f"{type(exc).__name__}: {exc}"})
    for r in results:
        print("  ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in r.items()))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
