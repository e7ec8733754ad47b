"""``virtualaxis frf``: Bode data (CSV + JSON) and plots (PNG) of mechanics, speed loop and position loop."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from virtualaxis.cli.common import add_config_argument
from virtualaxis.cli.outputs import add_force_argument, check_output_dir, staged_dir

#: files the command writes into --out
OUT_NAMES = ("frf.csv", "frf.json", "frf.png")
#: most frequency points: 1e5 points x 8 responses x 2 columns is ~20 MB of CSV; a log grid of 1e5 points over
#: six decades resolves a mode with 0.1 % damping by ~50 points across its half-power band
MAX_POINTS = 100_000


#: lowest --fmin [Hz]: below it s = j 2 pi f underflows the loop models' ratios (1e-320 Hz gave inf / nan)
FMIN_FLOOR_HZ = 1e-3


def register(sub) -> None:
    p = sub.add_parser("frf", help="frequency responses of mechanics, speed loop and position loop")
    add_config_argument(p)
    p.add_argument("--position", type=float, default=0.5, help="nut position as a fraction of the stroke")
    p.add_argument("--fmin", type=float, default=1.0, help="lowest frequency [Hz]")
    p.add_argument("--fmax", type=float, default=2000.0, help="highest frequency [Hz]")
    p.add_argument("--points", type=int, default=600, help=f"frequency points, log-spaced (2..{MAX_POINTS})")
    p.add_argument("--out", required=True, help="output folder (frf.csv, frf.json, frf.png)")
    add_force_argument(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from virtualaxis.cli.main import CliError
    from virtualaxis.config import load_axis_config
    from virtualaxis.plant.frf import bandwidth_hz, loop_frfs

    cfg = load_axis_config(args.config)
    nyquist = 0.5 / cfg.control.current_cycle_s
    if not (math.isfinite(args.fmin) and math.isfinite(args.fmax) and 0 < args.fmin < args.fmax):
        raise CliError(f"need finite 0 < --fmin < --fmax (got --fmin {args.fmin:g}, --fmax {args.fmax:g})")
    if args.fmin < FMIN_FLOOR_HZ:
        raise CliError(f"--fmin {args.fmin:g} Hz is below {FMIN_FLOOR_HZ:g} Hz (a {1 / FMIN_FLOOR_HZ / 60:.0f}-minute "
                       "period): no loop response is defined by the axis there and the numbers would overflow")
    if args.fmax > nyquist:
        raise CliError(f"--fmax {args.fmax:g} Hz is above {nyquist:g} Hz, the Nyquist frequency of the "
                       f"{cfg.control.current_cycle_s:g} s current cycle: the sampled loops have no response there")
    if not 2 <= args.points <= MAX_POINTS:
        raise CliError(f"--points must be 2 .. {MAX_POINTS} (got {args.points})")
    if not 0.0 <= args.position <= 1.0:
        raise CliError(f"--position is a fraction of the stroke (0..1) (got {args.position:g})")
    check_output_dir(args.out, args.force, OUT_NAMES, inputs=[args.config])
    nut = cfg.axis.nut_offset_m + (args.position - 0.5) * cfg.axis.stroke_m
    f = np.logspace(np.log10(args.fmin), np.log10(args.fmax), args.points)
    with np.errstate(all="ignore"):
        frfs = loop_frfs(cfg, f, nut)
    for key, fr in frfs.items():  # never write a silently non-finite response
        bad = ~(np.isfinite(fr.magnitude_db) & np.isfinite(fr.phase_deg))
        if bad.any():
            raise CliError(f"--fmin/--fmax: the {key} response is not finite at {f[np.flatnonzero(bad)[0]]:g} Hz "
                           f"with {args.config} (nothing written)")
    out = Path(args.out)
    with staged_dir(out) as stage:
        _write(stage, out, cfg, args, nut, f, frfs, bandwidth_hz)
    return 0


def _write(stage: Path, out: Path, cfg, args, nut: float, f: np.ndarray, frfs: dict, bandwidth_hz) -> None:
    cols = ["freq_hz"]
    data = [f]
    for key, fr in frfs.items():
        cols += [f"{key}_mag_db", f"{key}_phase_deg"]
        data += [fr.magnitude_db, fr.phase_deg]
    np.savetxt(stage / "frf.csv", np.column_stack(data), delimiter=",", header=",".join(cols), comments="", fmt="%.8g")
    summary = {
        "config": str(args.config),
        "nut_position_m": nut,
        "speed_loop_bandwidth_hz": bandwidth_hz(frfs["speed_closed_loop"]),
        "position_loop_bandwidth_hz": bandwidth_hz(frfs["position_closed_loop"]),
        "units": {k: fr.unit for k, fr in frfs.items()},
        "csv": str(out / "frf.csv"),
    }
    (stage / "frf.json").write_text(json.dumps(summary, indent=2))
    from virtualaxis.studies.plots import plot_bode

    plot_bode(frfs, stage / "frf.png", title=f"{cfg.axis.name}: nut at {nut:.3f} m")
    print(f"speed loop -3 dB: {summary['speed_loop_bandwidth_hz']:.1f} Hz, position loop -3 dB: "
          f"{summary['position_loop_bandwidth_hz']:.1f} Hz -> {out}")
