"""``virtualaxis rcsa``: natural frequencies and peak amplitudes of the seed 002 receptance-coupling model."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from virtualaxis.cli.common import parse_float_list
from virtualaxis.cli.outputs import (
    add_force_argument,
    check_output_dir,
    check_output_file,
    staged_dir,
    write_text_atomic,
)

if TYPE_CHECKING:  # (the model stack, scipy included, loads when the command runs: `virtualaxis --help` stays quick)
    from virtualaxis.rcsa.params import RcsaModel


def parse_positions(text: str | None, what: str = "--positions") -> list[float]:
    """'0.6,0.8,1.0' -> [0.6, 0.8, 1.0]; CliError on anything else (empty items, NaN, duplicates)."""
    from virtualaxis.cli.main import CliError

    if text is None:
        return []
    out = parse_float_list(text, what, hint=" (give metres, e.g. 0.6,0.8,1.0)", what="position")
    if len(set(out)) != len(out):
        raise CliError(f"{what}: duplicate position")
    return out


def check_positions(model: RcsaModel, positions: list[float], what: str) -> None:
    from virtualaxis.cli.main import CliError

    for pos in positions:
        try:
            model.check_position(pos, f"{what}:")
        except ValueError as exc:
            raise CliError(str(exc)) from None


def _none_for_nan(values: np.ndarray) -> list[float | None]:
    return [float(v) if math.isfinite(v) else None for v in values]


def plot_frf(model: RcsaModel, position_m: float, path: Path, modes: tuple[np.ndarray, np.ndarray]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from virtualaxis.rcsa.receptance import table_frf

    f = np.geomspace(5.0, 1000.0, 3000)
    h = np.empty(f.size, dtype=np.complex128)
    table_frf(f, position_m, model.parameter_vector(), h)
    fig, (ax_m, ax_p) = plt.subplots(2, 1, figsize=(8, 6), sharex=True, height_ratios=(3, 1))
    ax_m.loglog(f, np.abs(h), label="RCSA h_6a6a")
    freq, amp = modes
    ok = np.isfinite(freq)
    ax_m.plot(freq[ok], amp[ok], "rv", label="natural frequencies (band peaks)")
    for lo, hi in model.mode_bands_hz:
        ax_m.axvspan(lo, hi, color="0.92", zorder=0)
    ax_m.set_ylabel("|h| [m/N]")
    ax_m.set_title(f"table FRF at l = {position_m:g} m (grey: mode search bands)")
    ax_m.grid(True, which="both", alpha=0.3)
    ax_m.legend()
    ax_p.semilogx(f, np.degrees(np.angle(h)))
    ax_p.set_ylabel("phase [deg]")
    ax_p.set_xlabel("frequency [Hz]")
    ax_p.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    from virtualaxis.cli.main import CliError
    from virtualaxis.config import load_axis_config
    from virtualaxis.rcsa.params import rcsa_model_from_config

    cfg = load_axis_config(args.config)
    model = rcsa_model_from_config(cfg)
    positions = parse_positions(args.positions) or list(model.positions_m)
    if not positions:
        raise CliError(f"{args.config}: no positions: give --positions or rcsa.positions_m")
    check_positions(model, positions, "--positions")
    if args.json:
        check_output_file(args.json, args.force, "--json", inputs=[args.config])
    if args.plot:
        check_output_dir(args.plot, args.force, [f"frf_{p:.3f}m.png" for p in positions], "--plot",
                         inputs=[args.config])
    with staged_dir(args.plot) if args.plot else _nullstage() as stage:
        return _run(args, model, positions, stage)


class _nullstage:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc) -> None:
        return None


def _run(args: argparse.Namespace, model: RcsaModel, positions: list[float], stage: Path | None) -> int:
    from virtualaxis.rcsa.consistency import undamped_model
    from virtualaxis.rcsa.fe_shaft import fe_natural_frequencies_hz
    from virtualaxis.rcsa.identify import predict_modes

    results = []
    preds = predict_modes(model, positions)

    poles = predict_modes(undamped_model(model), positions)  # modes the damped FRF may hide (no band peak)
    print(
        f"{'position [m]':>12}  "
        + "  ".join(f"f{q + 1} [Hz]  |h{q + 1}| [m/N]" for q in range(len(model.mode_bands_hz)))
    )
    for pr, pole in zip(preds, poles, strict=True):
        row: dict = {
            "position_m": pr.position_m,
            "natural_frequencies_hz": _none_for_nan(pr.natural_frequencies_hz),
            "undamped_natural_frequencies_hz": _none_for_nan(pole.natural_frequencies_hz),
            "amplitudes_m_per_n": _none_for_nan(pr.amplitudes_m_per_n),
        }
        cells = []
        for f, a in zip(pr.natural_frequencies_hz, pr.amplitudes_m_per_n, strict=True):
            cells.append(f"{f:7.1f}  {a:12.3e}" if math.isfinite(f) else f"{'—':>7}  {'(no peak)':>12}")
        und = ", ".join("—" if not math.isfinite(f) else f"{f:.1f}" for f in pole.natural_frequencies_hz)
        print(f"{pr.position_m:12.3f}  " + "  ".join(cells) + f"   undamped: {und}")
        if args.fe_check:
            fe = fe_natural_frequencies_hz(model, pr.position_m)
            row["fe_natural_frequencies_hz"] = [float(v) for v in fe[(fe > 1.0) & (fe < 1000.0)]]
        results.append(row)
        if stage is not None:
            plot_frf(
                model,
                pr.position_m,
                stage / f"frf_{pr.position_m:.3f}m.png",
                (pr.natural_frequencies_hz, pr.amplitudes_m_per_n),
            )
    gaps = sum(1 for r in results for f in r["natural_frequencies_hz"] if f is None)
    if gaps:
        print(f"{gaps} mode(s) have no peak in their band (reported as null in JSON, '—' above); the undamped"
              " poles (undamped_natural_frequencies_hz) show where they are")
    if args.json:
        doc = {
            "config": str(args.config),
            "mode_bands_hz": [list(b) for b in model.mode_bands_hz],
            "joints": model.joints.as_dict(),
            "results": results,
        }
        write_text_atomic(args.json, json.dumps(doc, indent=1))
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "rcsa",
        help="receptance-coupling FRF model: natural frequencies and peak amplitudes per table position",
        description="Evaluate the seed 002 receptance-coupling model (eqs. 1-24) of the table FRF h_6a6a.",
    )
    p.add_argument("--config", required=True, help="axis config with an [rcsa] section")
    p.add_argument(
        "--positions", help="comma-separated nut positions l along the screw [m] (default: rcsa.positions_m)"
    )
    p.add_argument("--json", help="write the results here")
    p.add_argument("--plot", metavar="DIR", help="write one FRF plot per position into DIR")
    p.add_argument(
        "--fe-check", action="store_true", help="add the independent FE model's natural frequencies"
    )
    add_force_argument(p)
    p.set_defaults(func=run)
