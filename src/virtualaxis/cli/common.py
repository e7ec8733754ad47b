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


def parse_float_list(text: str, name: str, hint: str = "") -> list[float]:
    """'0.1,0.5,0.9' -> [0.1, 0.5, 0.9]; a CliError naming the option on an empty item, text or NaN/inf."""
    import math

    from virtualaxis.cli.errors import CliError

    vals = []
    for item in (x.strip() for x in text.split(",")):
        try:
            v = float(item)
        except ValueError:
            raise CliError(f"{name}: not a number: {item!r}{hint}") from None
        if not math.isfinite(v):
            raise CliError(f"{name}: not a finite number: {item!r}")
        vals.append(v)
    return vals
