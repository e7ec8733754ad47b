"""``virtualaxis modal``: natural frequencies, damping ratios and mode shapes vs nut position."""

from __future__ import annotations

import json
from pathlib import Path

from virtualaxis.cli.common import add_config_argument, parse_float_list


def register(sub) -> None:
    p = sub.add_parser("modal", help="modal analysis (natural frequencies, damping, mode shapes) vs nut position")
    add_config_argument(p)
    p.add_argument("--positions", default=None,
                   help="nut positions as fractions of the stroke, e.g. 0.1,0.5,0.9 (default: mid-stroke)")
    p.add_argument("--json", default=None, help="write results JSON here")
    p.add_argument("--plot", default=None, help="write mode-shape and frequency-vs-position PNGs to this folder")
    p.set_defaults(func=run)


def run(args) -> int:
    from virtualaxis.cli.main import CliError
    from virtualaxis.config import load_axis_config
    from virtualaxis.plant.modal import modal_analysis

    cfg = load_axis_config(args.config)
    fracs = parse_float_list(args.positions, "--positions") if args.positions else [0.5]
    for fr in fracs:
        if not 0.0 <= fr <= 1.0:
            raise CliError(f"--positions: {fr:g} is not a fraction of the stroke (0..1)")
    results = []
    for fr in fracs:
        table = (fr - 0.5) * cfg.axis.stroke_m
        nut = cfg.axis.nut_offset_m + table
        res = modal_analysis(cfg, nut)
        results.append({
            "stroke_fraction": fr,
            "table_position_m": table,
            "nut_position_m": nut,
            "natural_frequencies_hz": res.natural_frequencies_hz,
            "damping_ratios": res.damping_ratios,
            "body_names": res.body_names,
            "mode_shapes": res.mode_shapes,
            "spring_deformations": res.spring_deformations,
        })
        fs = ", ".join(f"{f:.1f}" for f in res.natural_frequencies_hz[:6])
        print(f"nut at {nut:.3f} m (stroke {fr:.2f}): {fs} Hz")
    doc = {"config": str(args.config), "nut_position_reference": "distance from the fixed (driven-end) bearing",
           "results": results}
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(doc, indent=2))
    if args.plot:
        from virtualaxis.studies.plots import plot_modal

        plot_modal(cfg, results, Path(args.plot))
    return 0
