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


def first_non_utf8_line(path) -> tuple[int, int]:
    """(1-based line number, byte value) of the first line of ``path`` that is not UTF-8; (0, 0) if none.
    Reads line by line (bounded memory)."""
    with open(path, "rb") as fh:
        for no, raw in enumerate(fh, start=1):
            try:
                raw.decode("utf-8")
            except UnicodeDecodeError as exc:
                return no, raw[exc.start]
    return 0, 0
