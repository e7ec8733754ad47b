"""Writing traces in the measured-trace format (``../shared/docs/trace-format.md``): CSV, SI units, header row."""

from __future__ import annotations

from pathlib import Path
from typing import TextIO

import numpy as np


class TraceWriter:
    """Streams trace rows to CSV chunk by chunk, so memory does not grow with duration."""

    def __init__(self, path: str | Path, columns: list[str]):
        self.path = Path(path)
        self.columns = ["t"] + [c for c in columns if c != "t"]
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh: TextIO = self.path.open("w", newline="")
        self._fh.write(",".join(self.columns) + "\n")
        self.rows = 0

    def write(self, data: dict[str, np.ndarray]) -> None:
        block = np.column_stack([np.asarray(data[c], dtype=float) for c in self.columns])
        np.savetxt(self._fh, block, delimiter=",", fmt="%.10g")
        self.rows += len(block)

    def close(self) -> None:
        self._fh.close()

    def __enter__(self) -> TraceWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def write_trace_csv(path: str | Path, data: dict[str, np.ndarray], columns: list[str] | None = None) -> Path:
    cols = columns or [c for c in data if c != "t"]
    with TraceWriter(path, cols) as w:
        w.write(data)
    return Path(path)


def read_trace_csv(path: str | Path) -> dict[str, np.ndarray]:
    """Plain reader for traces this package wrote (the diagnosis has its own validating reader)."""
    arr = np.genfromtxt(path, delimiter=",", names=True)
    return {name: np.asarray(arr[name], dtype=float) for name in arr.dtype.names}
