"""Helpers shared by CLI commands."""

from __future__ import annotations

import sys
from contextlib import contextmanager

from tqdm import tqdm


def add_config_argument(p, required: bool = True) -> None:
    p.add_argument("--config", required=required, help="axis config TOML (configs/*.toml)")


@contextmanager
def progress(total: int, desc: str):
    """A tqdm bar on stderr, silent when stderr is not a terminal and the job is short."""
    bar = tqdm(total=total, desc=desc, unit="cyc", unit_scale=True, file=sys.stderr, leave=False,
               disable=None, mininterval=0.5)
    try:
        yield bar
    finally:
        bar.close()


def parse_float_list(text: str, name: str, hint: str = "", what: str = "value") -> list[float]:
    """'0.1,0.5,0.9' -> [0.1, 0.5, 0.9]; a CliError naming the option on an empty list or item, text, NaN/inf,
    a subnormal number (1e-320: a typo, never a position or a gain) or a value given twice."""
    import math
    import sys

    from virtualaxis.cli.errors import CliError

    if not text.strip():
        raise CliError(f"{name}: empty list; give comma-separated numbers{hint} or leave the option out")
    vals = []
    for item in (x.strip() for x in text.split(",")):
        try:
            v = float(item)
        except ValueError:
            raise CliError(f"{name}: not a number: {item!r}{hint}") from None
        if not math.isfinite(v):
            raise CliError(f"{name}: not a finite number: {item!r}")
        if v != 0 and abs(v) < sys.float_info.min:
            raise CliError(f"{name}: {item!r} is a subnormal number (below 2.2e-308 in magnitude); give 0 or a "
                           "real value")
        if v in vals:
            raise CliError(f"{name}: duplicate {what} {item!r} (given twice)")
        vals.append(v)
    return vals
