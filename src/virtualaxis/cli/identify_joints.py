"""``virtualaxis identify-joints``: multi-position joint identification (seed 002 eqs. 25-26)."""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from virtualaxis.cli.outputs import add_force_argument, check_input_file, check_output_file, write_text_atomic
from virtualaxis.cli.rcsa import check_positions, parse_positions

if TYPE_CHECKING:  # (the model stack, scipy included, loads when the command runs: `virtualaxis --help` stays quick)
    from virtualaxis.rcsa.identify import MeasuredModes
    from virtualaxis.rcsa.params import RcsaModel


def _nn(values: np.ndarray) -> list[float | None]:
    return [float(v) if math.isfinite(v) else None for v in values]


def _position_report(model: RcsaModel, measured: MeasuredModes, joints) -> list[dict]:
    from virtualaxis.rcsa.identify import overall_error, predict_modes, relative_errors

    out = []
    preds = predict_modes(model, list(measured.positions_m), joints)
    for i, pr in enumerate(preds):
        mf, ma = measured.frequencies_hz[i], measured.amplitudes_m_per_n[i]
        out.append(
            {
                "position_m": pr.position_m,
                "measured_frequencies_hz": _nn(mf),
                "predicted_frequencies_hz": _nn(pr.natural_frequencies_hz),
                "frequency_relative_errors": _nn(relative_errors(pr.natural_frequencies_hz, mf)),
                "overall_frequency_error": overall_error(pr.natural_frequencies_hz, mf),
                "measured_amplitudes_m_per_n": _nn(ma),
                "predicted_amplitudes_m_per_n": _nn(pr.amplitudes_m_per_n),
                "amplitude_relative_errors": _nn(relative_errors(pr.amplitudes_m_per_n, ma)),
            }
        )
    return out


def _load_measured(args: argparse.Namespace, model: RcsaModel) -> MeasuredModes:
    from virtualaxis.cli.main import CliError
    from virtualaxis.rcsa.measured import modes_from_frfs, read_frf_csv, read_mode_table_csv

    if bool(args.frf) == bool(args.modes):
        raise CliError(
            "give exactly one of --frf (measured FRF CSV) or --modes (natural-frequency table CSV)"
        )
    if args.frf:
        measured = modes_from_frfs(read_frf_csv(args.frf), model)
    else:
        measured = read_mode_table_csv(args.modes, len(model.mode_bands_hz))
    return measured


def _report_gaps(measured: MeasuredModes, model: RcsaModel, source: str) -> None:
    for i, pos in enumerate(measured.positions_m):
        for q, (lo, hi) in enumerate(model.mode_bands_hz):
            if not math.isfinite(measured.frequencies_hz[i, q]):
                print(
                    f"note: {source}: position {pos:g} m, mode {q + 1}: no peak in {lo:g}..{hi:g} Hz"
                    " (a gap, left out of the objective)",
                    file=sys.stderr,
                )


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from virtualaxis.cli.main import CliError
    from virtualaxis.config import load_axis_config
    from virtualaxis.rcsa.config_writer import write_identified_config
    from virtualaxis.rcsa.identify import identify_joints
    from virtualaxis.rcsa.params import JOINT_SYMBOLS, JOINT_UNITS, rcsa_model_from_config
    from virtualaxis.rcsa.reproduce import nan_to_none

    cfg = load_axis_config(args.config)
    model = rcsa_model_from_config(cfg)
    ident = model.identification
    if ident is None:
        raise CliError(f"{args.config}: rcsa.identification: missing (search bounds are needed)")
    source = args.frf or args.modes
    train_pos = parse_positions(args.train_positions, "--train-positions")
    if not train_pos:
        raise CliError("--train-positions: give at least one position [m]")
    val_pos = parse_positions(args.validate_positions, "--validate-positions")
    if set(train_pos) & set(val_pos):
        raise CliError("--validate-positions must not repeat a training position")
    check_positions(model, train_pos + val_pos, "position")
    for opt, val, lo, hi in (("--generations", args.generations, 1, 100_000),
                             ("--population", args.population, 1, 1000),
                             ("--seed", args.seed, 0, 2**63 - 1)):
        if val is not None and not lo <= val <= hi:
            raise CliError(f"{opt} must be {lo} .. {hi} (got {val})")
    from virtualaxis.cli.common import check_jobs

    if args.workers is not None:
        check_jobs(args.workers, "--workers")
    else:  # (the config's value: bounded like the option)
        check_jobs(int(ident.workers), f"{args.config}: rcsa.identification.workers")
    if args.frequencies_only and args.amplitude_weight is not None:
        raise CliError("--frequencies-only and --amplitude-weight are alternatives (--frequencies-only is a weight "
                       "of 0); give one of them")
    weight = ident.amplitude_weight if args.amplitude_weight is None else args.amplitude_weight
    if args.frequencies_only:
        weight = 0.0
    if not (math.isfinite(weight) and weight >= 0):
        raise CliError(f"--amplitude-weight: must be a number >= 0 (got {weight})")
    inputs = [args.config] + [x for x in (args.frf, args.modes) if x]
    for opt, val in (("--frf", args.frf), ("--modes", args.modes)):
        if val:
            check_input_file(val, opt)
    if args.json:
        check_output_file(args.json, args.force, "--json", inputs=inputs)
    if args.write_config:
        check_output_file(args.write_config, args.force, "--write-config", inputs=inputs)
        if args.json and Path(args.json).resolve() == Path(args.write_config).resolve():
            raise CliError("--json and --write-config name the same file")
    measured = _load_measured(args, model)
    for pos in measured.positions_m:  # (a row off the screw is no training position: it was dropped silently)
        check_positions(model, [float(pos)], f"{source}: position_m")
    try:
        train = measured.select(train_pos, source)
        val = measured.select(val_pos, source) if val_pos else None
    except ValueError as exc:
        raise CliError(str(exc)) from None
    if not np.any(np.isfinite(train.frequencies_hz)):  # (before the gap notes: the error is the one line)
        raise CliError(f"{source}: no natural frequency found at any training position")
    _report_gaps(train, model, source)
    use_amp = weight > 0
    if use_amp and not np.any(np.isfinite(train.amplitudes_m_per_n)):
        print("note: no amplitudes in the data; identifying from natural frequencies only", file=sys.stderr)
    generations = args.generations or ident.generations
    population = args.population or ident.population_per_parameter
    workers = args.workers or ident.workers
    seed = ident.seed if args.seed is None else args.seed
    with tqdm(total=generations, desc="identify-joints", unit="gen", file=sys.stderr) as bar:
        res = identify_joints(
            model,
            train,
            lower=ident.lower,
            upper=ident.upper,
            population_per_parameter=population,
            generations=generations,
            seed=seed,
            workers=workers,
            relative_tolerance=ident.relative_tolerance,
            amplitude_weight=weight,
            progress=lambda g: bar.update(1),
        )
    doc = {
        "config": str(args.config),
        "data": str(source),
        "train_positions_m": train_pos,
        "validate_positions_m": val_pos,
        "identified": {s: getattr(res.joints, s) for s in JOINT_SYMBOLS},
        "units": dict(zip(JOINT_SYMBOLS, JOINT_UNITS, strict=True)),
        "objective": res.objective,
        "amplitude_weight": weight,
        "generations": res.generations,
        "population": population * len(JOINT_SYMBOLS),
        "objective_evaluations": res.objective_evaluations,
        "wall_time_s": res.wall_time_s,
        "seed": seed,
        "train": _position_report(model, train, res.joints),
        "validate": _position_report(model, val, res.joints) if val is not None else [],
    }
    for s, u in zip(JOINT_SYMBOLS, JOINT_UNITS, strict=True):
        print(f"{s:>5} = {getattr(res.joints, s):.4g} {u}")
    print(
        f"objective (eq. 26) = {res.objective:.5f} after {res.generations} generations,"
        f" {res.wall_time_s:.1f} s"
    )
    for tag in ("train", "validate"):
        for r in doc[tag]:
            errs = ", ".join("—" if e is None else f"{100 * e:.2f} %" for e in r["frequency_relative_errors"])
            print(f"{tag:>8} l = {r['position_m']:g} m: frequency errors {errs}")
    if args.json:
        write_text_atomic(args.json, json.dumps(nan_to_none(doc), indent=1, allow_nan=False))
    if args.write_config:
        stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d")
        note = (
            f"identified {stamp} by virtualaxis identify-joints from {source}, train positions "
            + ",".join(f"{p:g}" for p in train_pos)
            + f" m, objective {res.objective:.4g}"
        )
        from virtualaxis.cli.outputs import atomic_path

        with atomic_path(args.write_config) as tmp:
            write_identified_config(args.config, tmp, res.joints, note)
        print(f"wrote {args.write_config}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "identify-joints",
        help="identify the eight joint parameters from measured FRFs at several table positions",
        description="Multi-position joint identification (seed 002): eq. 26 with differential evolution.",
    )
    p.add_argument("--config", required=True, help="axis config with [rcsa] and [rcsa.identification]")
    p.add_argument(
        "--frf", help="measured FRF CSV: position_m,freq_hz,re,im or position_m,freq_hz,mag,phase_deg"
    )
    p.add_argument(
        "--modes", help="natural-frequency table CSV: position_m,order,freq_hz[,amplitude_m_per_n]"
    )
    p.add_argument("--train-positions", required=True, help="comma-separated positions [m] to identify on")
    p.add_argument("--validate-positions", help="comma-separated held-out positions [m] to predict")
    p.add_argument("--json", help="write identified parameters, objective and per-position errors here")
    p.add_argument("--write-config", metavar="TOML", help="write the config with the identified joints here")
    p.add_argument("--generations", type=int, help="override rcsa.identification.generations")
    p.add_argument("--population", type=int, help="override rcsa.identification.population_per_parameter")
    p.add_argument("--workers", type=int, help="override rcsa.identification.workers")
    p.add_argument("--seed", type=int, help="override rcsa.identification.seed")
    p.add_argument("--frequencies-only", action="store_true", help="leave the amplitude terms out of eq. 26")
    p.add_argument(
        "--amplitude-weight", type=float, help="weight of eq. 26's amplitude terms (rcsa.identification)"
    )
    add_force_argument(p)
    p.set_defaults(func=run)
