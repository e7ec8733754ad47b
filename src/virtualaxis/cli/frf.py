"""``virtualaxis frf``: Bode data (CSV + JSON) and plots (PNG) of mechanics, speed loop and position loop."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from virtualaxis.cli.common import add_config_argument


def register(sub) -> None:
    p = sub.add_parser("frf", help="frequency responses of mechanics, speed loop and position loop")
    add_config_argument(p)
    p.add_argument("--position", type=float, default=0.5, help="nut position as a fraction of the stroke")
    p.add_argument("--fmin", type=float, default=1.0, help="lowest frequency [Hz]")
    p.add_argument("--fmax", type=float, default=2000.0, help="highest frequency [Hz]")
    p.add_argument("--points", type=int, default=600)
    p.add_argument("--out", required=True, help="output folder (frf.csv, frf.json, frf.png)")
    p.set_defaults(func=run)


def run(args) -> int:
    from virtualaxis.cli.main import CliError
    from virtualaxis.config import load_axis_config
    from virtualaxis.plant.frf import bandwidth_hz, loop_frfs

    cfg = load_axis_config(args.config)
    if not (0 < args.fmin < args.fmax):
        raise CliError("need 0 < --fmin < --fmax")
    if not 0.0 <= args.position <= 1.0:
        raise CliError("--position is a fraction of the stroke (0..1)")
    nut = cfg.axis.nut_offset_m + (args.position - 0.5) * cfg.axis.stroke_m
    f = np.logspace(np.log10(args.fmin), np.log10(args.fmax), args.points)
    frfs = loop_frfs(cfg, f, nut)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cols = ["freq_hz"]
    data = [f]
    for key, fr in frfs.items():
        cols += [f"{key}_mag_db", f"{key}_phase_deg"]
        data += [fr.magnitude_db, fr.phase_deg]
    np.savetxt(out / "frf.csv", np.column_stack(data), delimiter=",", header=",".join(cols), comments="", fmt="%.8g")
    summary = {
        "config": str(args.config),
        "nut_position_m": nut,
        "speed_loop_bandwidth_hz": bandwidth_hz(frfs["speed_closed_loop"]),
        "position_loop_bandwidth_hz": bandwidth_hz(frfs["position_closed_loop"]),
        "units": {k: fr.unit for k, fr in frfs.items()},
        "csv": str(out / "frf.csv"),
    }
    (out / "frf.json").write_text(json.dumps(summary, indent=2))
    from virtualaxis.studies.plots import plot_bode

    plot_bode(frfs, out / "frf.png", title=f"{cfg.axis.name}: nut at {nut:.3f} m")
    print(f"speed loop -3 dB: {summary['speed_loop_bandwidth_hz']:.1f} Hz, position loop -3 dB: "
          f"{summary['position_loop_bandwidth_hz']:.1f} Hz -> {out}")
    return 0
