"""``virtualaxis simulate``: run the axis on a command profile and write a trace (CSV) and a summary (JSON)."""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path

import numpy as np

from virtualaxis.cli.common import add_config_argument, progress
from virtualaxis.cli.errors import CliError
from virtualaxis.cli.outputs import add_force_argument, atomic_path, check_free_space, check_output_file

#: default bound on the trace files one run writes [MiB]; ``--max-output-mb`` raises it
DEFAULT_MAX_OUTPUT_MB = 2048.0
#: --out suffixes: what the trace writer writes (CSV, or NPZ for .npz); a .xlsx would hold CSV under a lie
TRACE_SUFFIXES = ("", ".csv", ".txt", ".dat", ".npz")
#: estimated CSV bytes per value ("%.10g" plus the separator; measured 11-14 on simulated traces)
CSV_BYTES_PER_VALUE = 14


def register(sub) -> None:
    p = sub.add_parser("simulate", help="simulate the axis on a command profile; write trace CSV and JSON summary")
    add_config_argument(p)
    p.add_argument("--profile", required=True, help="sine:..., ptp:..., step:..., chirp:..., circle:..., file:F.csv")
    p.add_argument("--duration", type=float, default=None, help="simulated seconds (default: the profile's own)")
    p.add_argument("--out", required=True, help="trace file: .csv (.txt, .dat or no suffix: CSV too), or .npz for a "
                   "NumPy archive (a circle writes <stem>_x<suffix> and <stem>_y<suffix>)")
    p.add_argument("--json", default=None, help="summary JSON")
    p.add_argument("--seed", type=int, default=None, help="noise seed (default: simulation.seed of the config)")
    p.add_argument("--extras", action="store_true", help="also write internal signals (currents, friction, ...)")
    p.add_argument("--max-output-mb", type=float, default=DEFAULT_MAX_OUTPUT_MB,
                   help=f"refuse runs whose trace files would exceed this size (default {DEFAULT_MAX_OUTPUT_MB:g} MiB)")
    add_force_argument(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from virtualaxis.cli.outputs import same_file as same_path
    from virtualaxis.cli.outputs import write_text_atomic
    from virtualaxis.config import load_axis_config
    from virtualaxis.sim.batch import EXTRA_COLUMNS, columns_for, rows_to_columns
    from virtualaxis.sim.profiles import check_limits, parse_profile, sample_profile
    from virtualaxis.sim.simulator import AxisSimulator
    from virtualaxis.sim.trace_io import TraceWriter, prepare_csv_formatter, trace_format_for

    if not args.out.strip():
        raise CliError("--out: empty path")
    if args.out.endswith(("/", os.sep)):  # (Path() would drop the slash and write a file of that name)
        raise CliError(f"--out: {args.out} ends with '/', which names a folder; give a file name")
    cfg = load_axis_config(args.config)
    if args.seed is not None and not 0 <= args.seed < 2**63:
        raise CliError(f"--seed must be an integer 0 .. 2^63-1 (got {args.seed})")
    if not (math.isfinite(args.max_output_mb) and args.max_output_mb > 0):
        raise CliError(f"--max-output-mb must be a positive number (got {args.max_output_mb:g})")
    prof = parse_profile(args.profile, cfg)
    dur = float(args.duration if args.duration is not None else prof.natural_duration_s)
    what = "--duration" if args.duration is not None else f"the duration of profile '{args.profile}'"
    if not (math.isfinite(dur) and dur > 0):
        raise CliError(f"{what} must be a finite number > 0 s (got {dur:g})")
    cyc = cfg.control.position_cycle_s
    if dur < cyc:
        raise CliError(f"{what}: {dur:g} s is shorter than one position cycle ({cyc:g} s of the config): the trace "
                       "would hold the start only")
    n_f = dur / cyc + 1.0  # a float first: 1e308 s must be refused by the size bound, not overflow an int
    out_path = Path(args.out)
    cols = columns_for(cfg) + (list(EXTRA_COLUMNS) if args.extras else [])
    est_bytes = n_f * (len(cols) + 1) * CSV_BYTES_PER_VALUE * len(prof.axes)
    n = int(round(dur / cyc)) + 1 if est_bytes <= args.max_output_mb * 2**20 else int(min(n_f, 2**62))
    if est_bytes > args.max_output_mb * 2**20:
        raise CliError(
            f"{what}: {dur:g} s at the {cyc:g} s position cycle are {n:.3g} rows x {len(cols) + 1} columns"
            f"{' x 2 axes' if len(prof.axes) > 1 else ''}, ~{est_bytes / 2**20:.3g} MiB of trace; the bound is "
            f"--max-output-mb {args.max_output_mb:g} (shorten the run or raise the bound)"
        )
    paths = {name: out_path if len(prof.axes) == 1 else out_path.with_name(f"{out_path.stem}_{name}{out_path.suffix}")
             for name in prof.axes}
    inputs = [args.config] + ([prof.source_path] if prof.source_path else [])
    for path in paths.values():
        check_output_file(path, args.force, "--out", inputs=inputs)
    if args.json:
        if any(same_path(args.json, pth) for pth in paths.values()):
            raise CliError(f"--json: {args.json} is also the trace output (--out)")
        check_output_file(args.json, args.force, "--json", inputs=inputs)
    if Path(args.out).suffix.lower() not in (*TRACE_SUFFIXES, ".parquet", ".pq"):  # (Parquet: trace_io says why)
        raise CliError(f"--out: {args.out}: a trace is written as CSV (.csv, .txt, .dat or no suffix) or as a NumPy "
                       f"archive (.npz), not as {Path(args.out).suffix!r}")
    check_free_space(out_path.parent, est_bytes)
    prof.check_duration(dur)
    peaks = check_limits(prof, cfg, dur, cyc)
    summary_axes = {}
    start0 = time.perf_counter()  # one-off start-up (numba kernel load), reported apart as startup_s
    AxisSimulator(cfg, seed=args.seed).run_arrays(np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1))
    if trace_format_for(out_path) == "csv":  # the CSV formatter's load belongs to the start-up too
        prepare_csv_formatter()
    wall0 = time.perf_counter()
    chunk = 10000
    pos_limit = 10.0 * cfg.axis.stroke_m + 1.0  # [m] beyond this the run has diverged (see below)
    for name in prof.axes:
        path = paths[name]
        t_first = np.zeros(1)
        p0 = sample_profile(prof, t_first, dur)[name][0][0]
        sim = AxisSimulator(cfg, seed=args.seed, initial_position_m=float(p0))
        sim.enable(True)
        sq = 0.0
        mx = 0.0
        sq_fe = 0.0
        with (atomic_path(path) as tmp, TraceWriter(tmp, cols, threaded=True) as w,
              progress(n, f"simulate {name}") as bar):
            for a in range(0, n, chunk):
                b = min(n, a + chunk)
                t = np.arange(a, b) * cyc
                p, v, acc = sample_profile(prof, t, dur)[name]
                rows = sim.run_arrays(p, v, acc, np.zeros(b - a))
                data = rows_to_columns(cfg, rows, extras=args.extras)
                pos = data.get("pos_meas", data["pos_cmd"])
                # diverged: a non-finite value in any column, or a table beyond every end stop (the stroke is at
                # most 100 m and the end stops sit behind its ends: 10 strokes + 1 m away is no motion of an axis)
                non_finite = np.zeros(len(pos), dtype=bool)
                for col in data.values():
                    non_finite |= ~np.isfinite(col)
                bad = non_finite | (np.abs(pos) > pos_limit)
                if bad.any():
                    i_bad = int(np.flatnonzero(bad)[0])
                    t_bad = float(t[i_bad])
                    what = ("non-finite values" if non_finite[i_bad]
                            else f"position {pos[i_bad]:.3g} m, beyond +-{pos_limit:g} m")
                    raise CliError(f"axis {name}: the simulation diverged ({what} at t = {t_bad:g} s); "
                                   f"the config's gains or parameters do not give a stable axis: {args.config}")
                w.write(data)
                err = data["pos_meas"] - data["pos_cmd"]
                sq += float(np.sum(err**2))
                sq_fe += float(np.sum(data["following_error"] ** 2))
                mx = max(mx, float(np.max(np.abs(err))))
                bar.update(b - a)
        summary_axes[name] = {
            "trace": str(path),
            "rmse_tracking_error_m": (sq / n) ** 0.5,
            "max_tracking_error_m": mx,
            "rms_following_error_m": (sq_fe / n) ** 0.5,
            **peaks[name],
        }
    wall = time.perf_counter() - wall0
    first = summary_axes[prof.axes[0]]
    summary = {
        "config": str(args.config),
        "profile": args.profile,
        "simulated_s": dur,
        "wall_s": wall,
        "startup_s": wall0 - start0,
        "real_time_factor": dur * len(prof.axes) / wall if wall > 0 else None,
        "real_time_factor_definition": "simulated_s per wall_s; wall_s = simulation + writing and closing the trace"
        " (not imports, config loading or the one-off numba kernel load, which is startup_s)",
        "rmse_tracking_error_m": first["rmse_tracking_error_m"],
        "max_tracking_error_m": first["max_tracking_error_m"],
        "tracking_error_definition": "pos_meas (linear scale) - pos_cmd, sampled at the position-loop cycle",
        "axes": summary_axes,
    }
    if args.json:
        write_text_atomic(args.json, json.dumps(summary, indent=2, allow_nan=False))
    rmse_um = first["rmse_tracking_error_m"] * 1e6
    max_um = first["max_tracking_error_m"] * 1e6
    written = ", ".join(a["trace"] for a in summary_axes.values())  # (a circle: one trace per axis)
    print(f"simulated {dur:g} s in {wall:.2f} s wall; RMSE tracking error {rmse_um:.2f} um, max {max_um:.2f} um"
          f" -> {written}")
    return 0
