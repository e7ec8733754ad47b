"""Errors raised while loading configuration and input files."""

from __future__ import annotations


class ConfigError(ValueError):
    """A configuration problem, always naming the file and the key (``section.key``).

    ``str(err)`` is the one line a user sees, e.g.
    ``configs/x.toml: mechanics.lead_m: must be > 0 (got 0.0)``.
    """

    def __init__(self, file: str, key: str, message: str):
        self.file = str(file)
        self.key = key
        self.message = message
        super().__init__(f"{self.file}: {key}: {message}" if key else f"{self.file}: {message}")


class InputError(ValueError):
    """A problem in a data file (trace, move list, FRF table), naming file, row and column."""

    def __init__(self, file: str, message: str, row: int | None = None, column: str | None = None):
        self.file = str(file)
        self.row = row
        self.column = column
        where = self.file
        if row is not None:
            where += f": row {row}"
        if column is not None:
            where += f": column {column}"
        super().__init__(f"{where}: {message}")
