"""Trace CSV files for the diagnosis tests: written by ``virtualaxis simulate`` (the command a user types, in
process), then read and rewritten row by row as a recorder or a user would change them."""

from __future__ import annotations

import csv
from pathlib import Path

from virtualaxis.cli.main import main
from virtualaxis.diagnosis.bench import BALLSCREW_CONFIG


def simulated(out: Path, profile: str, duration_s: float, config: Path = BALLSCREW_CONFIG) -> Path:
    """``virtualaxis simulate`` of ``profile`` on ``config`` into ``out`` (sensor noise on, as measured)."""
    assert main(["simulate", "--config", str(config), "--profile", profile, "--duration", str(duration_s),
                 "--out", str(out)]) == 0
    return out


def read_rows(path: Path) -> tuple[list[str], list[list[str]]]:
    """The header and the data rows as text."""
    with Path(path).open() as fh:
        rows = list(csv.reader(fh))
    return rows[0], rows[1:]


def write_rows(path: Path, header: list[str], rows) -> Path:
    """``rows`` (lists of values, or a 2-D array) under ``header``."""
    rows = rows.tolist() if hasattr(rows, "tolist") else rows
    with Path(path).open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)
    return Path(path)
