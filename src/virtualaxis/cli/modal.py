"""``virtualaxis modal``: natural frequencies, damping ratios and mode shapes vs nut position."""

from __future__ import annotations

import json
from pathlib import Path

from virtualaxis.cli.common import add_config_argument, parse_float_list
from virtualaxis.cli.outputs import (
    add_force_argument,
    check_output_dir,
    check_output_file,
    staged_dir,
    write_text_atomic,
)

#: files ``--plot`` writes
PLOT_NAMES = ("frequencies_vs_position.png", "mode_shapes.png")
#: most positions one run evaluates (each is a modal analysis of the full model, ~ms; the JSON grows with it)
MAX_POSITIONS = 10_000


def register(sub) -> None:
    p = sub.add_parser("modal", help="modal analysis (natural frequencies, damping, mode shapes) vs nut position")
    add_config_argument(p)
    p.add_argument("--positions", default=None,
                   help="nut positions as fractions of the stroke, e.g. 0.1,0.5,0.9 (default: mid-stroke)")
    p.add_argument("--json", default=None, help="write results JSON here")
    p.add_argument("--plot", default=None, help="write mode-shape and frequency-vs-position PNGs to this folder")
    add_force_argument(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from virtualaxis.cli.main import CliError
    from virtualaxis.config import load_axis_config
    from virtualaxis.plant.modal import modal_analysis

    cfg = load_axis_config(args.config)
    fracs = parse_float_list(args.positions, "--positions") if args.positions is not None else [0.5]
    for fr in fracs:
        if not 0.0 <= fr <= 1.0:
            raise CliError(f"--positions: {fr:g} is not a fraction of the stroke (0..1)")
    if len(fracs) > MAX_POSITIONS:
        raise CliError(f"--positions: {len(fracs)} positions; at most {MAX_POSITIONS}")
    if args.json:
        check_output_file(args.json, args.force, "--json", inputs=[args.config])
    if args.plot:
        check_output_dir(args.plot, args.force, PLOT_NAMES, "--plot", inputs=[args.config])
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
        write_text_atomic(args.json, json.dumps(doc, indent=2))
    if args.plot:
        from virtualaxis.studies.plots import plot_modal

        with staged_dir(args.plot) as stage:
            plot_modal(cfg, results, Path(stage))
    return 0
