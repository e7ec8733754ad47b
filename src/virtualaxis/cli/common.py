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


def parse_float_list(text: str, name: str) -> list[float]:
    from virtualaxis.cli.main import CliError

    try:
        vals = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise CliError(f"{name}: expected comma-separated numbers, got '{text}'") from None
    if not vals:
        raise CliError(f"{name}: no values given")
    return vals
