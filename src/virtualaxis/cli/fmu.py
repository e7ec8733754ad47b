"""``virtualaxis fmu``: export the configured axis as an FMI 2.0 co-simulation FMU (docs/fmu.md)."""

from __future__ import annotations

from pathlib import Path

from virtualaxis.cli.common import add_config_argument
from virtualaxis.cli.errors import CliError
from virtualaxis.cli.outputs import add_force_argument, atomic_path, check_output_file


def register(sub) -> None:
    from virtualaxis.fmu.export import INTERFACES

    p = sub.add_parser("fmu", help="export the axis as an FMI 2.0 co-simulation FMU (needs pythonfmu)")
    add_config_argument(p)
    p.add_argument("--out", required=True, help="the FMU file to write (.fmu)")
    p.add_argument("--interface", choices=INTERFACES, default="position",
                   help="what the importing tool drives: motor torque (it runs the speed and position loops), "
                        "speed set-point (it runs the position loop) or position set-point (default; the "
                        "drive's cascade inside)")
    p.add_argument("--step", type=float, default=None,
                   help="default communication step [s] written into the FMU: a whole number of current-loop "
                        "cycles (default: one position-loop cycle)")
    add_force_argument(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from virtualaxis.config import load_axis_config
    from virtualaxis.fmu.export import build_fmu, check_step

    try:
        import pythonfmu  # noqa: F401 - the optional dependency of this command
    except ImportError:
        raise CliError("the fmu command needs pythonfmu, which is not installed: "
                       "pip install 'virtualaxis[fmu]'") from None
    out = Path(args.out)
    if not args.out.strip():
        raise CliError("--out: empty path")
    if out.suffix.lower() != ".fmu":
        raise CliError(f"--out: {args.out}: an FMU file ends in .fmu")
    cfg = load_axis_config(args.config)
    step = check_step(cfg, args.step)
    check_output_file(out, args.force, "--out", inputs=[args.config])
    with atomic_path(out) as tmp:
        build_fmu(args.config, tmp, args.interface, step)
    print(f"{out}: FMI 2.0 co-simulation FMU of '{cfg.axis.name}', {args.interface} interface, communication step "
          f"{step:g} s (a multiple of the {cfg.control.current_cycle_s:g} s current cycle); needs a Python with "
          "virtualaxis installed (docs/fmu.md)")
    return 0
