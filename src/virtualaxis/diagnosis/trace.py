"""Reading and validating measured traces (``docs/reference/trace-format.md``).

A trace is one CSV file with a header row, SI units. :func:`read_trace` returns a :class:`Trace` on a
uniform time grid or raises :class:`~virtualaxis.config.errors.InputError` naming the file, the row
(the line number in the file, the header being line 1) and the column. Problems that can be repaired
safely (timing jitter, a few isolated NaNs, a motor-angle offset) are repaired and recorded in
``Trace.warnings`` so that the report says what was done.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from virtualaxis.config.axis import read_text_file
from virtualaxis.config.errors import ConfigError, InputError, first_non_utf8_line
from virtualaxis.config.tomlfile import TomlError, parse_toml
from virtualaxis.sim.trace_io import read_trace_npz

POSITION_COLUMNS = ("pos_meas", "pos_fb", "motor_pos")
OPTIONAL_COLUMNS = ("vel_meas", "torque_meas", "current_q", "force_drive", "force_ext")
KNOWN_COLUMNS = ("t", "pos_cmd", *POSITION_COLUMNS, *OPTIONAL_COLUMNS)
#: channels compared with the simulation (force_ext is an input, pos_cmd the command)
RESIDUAL_CHANNELS = ("pos_meas", "pos_fb", "motor_pos", "vel_meas", "torque_meas", "current_q", "force_drive")
CHANNEL_UNITS = {
    "pos_meas": "m",
    "pos_fb": "m",
    "motor_pos": "rad",
    "vel_meas": "m/s",
    "torque_meas": "N m",
    "current_q": "A",
    "force_drive": "N",
}

# a jitter below this fraction of the sample period is accepted without resampling
_JITTER_TOLERANCE = 1e-6
# a time step above this multiple of the median period is a gap
_GAP_FACTOR = 1.5
# isolated NaN runs up to this many samples are interpolated (with a warning)
_MAX_NAN_RUN = 3


@dataclass
class Trace:
    """One measured run on a uniform time grid (``t`` starts where the file starts)."""

    name: str
    path: str
    t: np.ndarray
    columns: dict[str, np.ndarray]
    metadata: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    @property
    def dt_s(self) -> float:
        return float(self.t[1] - self.t[0]) if self.t.size > 1 else 0.0

    @property
    def duration_s(self) -> float:
        return float(self.t[-1] - self.t[0])

    @property
    def pos_cmd(self) -> np.ndarray:
        return self.columns["pos_cmd"]

    @property
    def force_ext(self) -> np.ndarray | None:
        return self.columns.get("force_ext")

    def channels(self) -> list[str]:
        """Measured channels that can be compared with the simulation."""
        return [c for c in RESIDUAL_CHANNELS if c in self.columns]

    def max_speed_m_s(self) -> float:
        """The command's top speed [m/s]; 0 for a command that does not move (a gradient over time stamps that
        are not exactly uniform leaves a rounding residue of a constant)."""
        x = self.pos_cmd
        if self.t.size <= 2 or float(np.max(x) - np.min(x)) == 0.0:
            return 0.0
        return float(np.max(np.abs(np.gradient(x, self.t))))


def _err(path: str, msg: str, row: int | None = None, column: str | None = None) -> InputError:
    return InputError(path, msg, row, column)


#: most samples per trace the diagnosis reads. Every candidate fit simulates each trace several times and the
#: workers hold the trace and its predictions: measured on a 120 000-sample trace (120 s at 1 kHz, `diagnose
#: --jobs 2`): 15 min wall, 415 MiB in the main process, 850 MiB with the workers (docs/bad-input.md); both grow
#: linearly, so 200 000 samples (3.3 min at 1 kHz) are ~25 min and ~1.4 GiB. A longer trace is refused before
#: it is read, naming this bound; cut it into segments or decimate it.
MAX_TRACE_SAMPLES = 200_000
#: a CSV row of the trace format is ~100-150 bytes; files beyond this per allowed sample are refused unread
_MAX_BYTES_PER_ROW = 512
_MAX_HEADER_CHARS = 65536
#: lines parsed per chunk (bounded memory while reading; the progress bar advances per chunk)
_CHUNK_LINES = 50_000


#: unit suffixes a header may carry after a column name (``pos_meas_m``, ``current_q_a``)
UNIT_SUFFIXES = frozenset({"s", "ms", "us", "m", "mm", "um", "nm", "rad", "deg", "rev", "m_s", "mm_s", "mm_min",
                           "nm_m", "n_m", "n", "a", "ma", "v", "rpm"})


def _meant_column(header_name: str) -> str:
    """The column name a header entry written with a unit or in another case stands for (``"T [s]"`` -> ``"t"``)."""
    return header_name.split("[")[0].split("(")[0].strip().lower()


def _known_column_meant(header_name: str) -> str | None:
    """The trace column a header entry stands for when it is written with a unit, in brackets or as a suffix, or in
    another case (``"T [s]"``, ``"t_s"``, ``"pos_meas_mm"``), else None."""
    meant = _meant_column(header_name)
    if meant in KNOWN_COLUMNS:
        return meant
    return next((c for c in KNOWN_COLUMNS if meant.startswith(c + "_") and meant[len(c) + 1:] in UNIT_SUFFIXES),
                None)


def _fast_chunk(lines: list[str], ncols: int, use: list[int]) -> np.ndarray | None:
    """Parse a chunk of well-formed numeric lines in C; None when any line needs the careful path."""
    for ln in lines:
        if ln.count(",") != ncols - 1 or '"' in ln or ",," in ln or ln.startswith(",") or not ln.strip(" \r\n,"):
            return None
        if ln.rstrip("\r\n").endswith(","):
            return None
    try:
        arr = np.loadtxt(lines, delimiter=",", dtype=float, usecols=use, ndmin=2, comments=None)
    except ValueError:
        return None
    return arr if arr.shape[0] == len(lines) else None


def _careful_chunk(path: str, lines: list[str], first_line_no: int, header: list[str], use: list[int]
                   ) -> tuple[np.ndarray, list[int]]:
    """Row-by-row parse naming the line and column of the first bad value (empty fields are NaN; a blank line is
    skipped, a row of empty fields is a row of missing values). Returns the rows and the file line of each."""
    rows: list[list[float]] = []
    kept: list[int] = []
    reader = csv.reader(lines)
    try:
        for k, rec in enumerate(reader):
            line_no = first_line_no + k
            if not rec or (len(rec) == 1 and not rec[0].strip()):
                continue
            if len(rec) < len(header):
                missing = header[len(rec):]
                raise _err(path, f"has {len(rec)} fields, the header has {len(header)}: no value for "
                           f"{', '.join(missing)}", line_no, missing[0])
            if len(rec) > len(header):
                raise _err(path, f"has {len(rec)} fields, the header has {len(header)}: {len(rec) - len(header)} "
                           f"beyond the last column", line_no, header[-1])
            vals = []
            for i in use:
                s = rec[i].strip()
                try:
                    vals.append(float(s) if s else math.nan)
                except ValueError:
                    raise _err(path, f"not a number: {s!r}", line_no, header[i]) from None
            rows.append(vals)
            kept.append(line_no)
    except csv.Error as exc:
        raise _err(path, f"not a readable CSV file ({exc})", first_line_no) from None
    return np.asarray(rows, dtype=float).reshape(-1, len(use)), kept


def _parse_csv(path: Path, max_samples: int | None = None
               ) -> tuple[list[str], list[str], np.ndarray, list[str], np.ndarray | None]:
    """Stream a trace CSV in chunks of :data:`_CHUNK_LINES` lines (a progress bar on a terminal) keeping only the
    known columns. Returns (header, kept column names, data, warnings, the file line of each data row or None when
    row k is line k + 2). A file with more than ``max_samples`` rows (default :data:`MAX_TRACE_SAMPLES`) is
    refused, by its size before it is read where possible."""
    from itertools import islice

    from tqdm import tqdm

    sp = str(path)
    limit = MAX_TRACE_SAMPLES if max_samples is None else max_samples
    if path.is_dir():
        raise _err(sp, "is a folder, not a trace file")
    if path.exists() and not path.is_file():
        raise _err(sp, "not a regular file (a device, pipe or socket); give a trace file")
    try:
        size = path.stat().st_size
        if size > limit * _MAX_BYTES_PER_ROW:
            raise _err(sp, f"{size / 2**20:.3g} MiB; the diagnosis reads at most {limit:,} samples per trace "
                           f"(~{limit * _MAX_BYTES_PER_ROW / 2**20:.3g} MiB of CSV at most; bounded memory and fit "
                           "time): cut the trace into segments or decimate it")
        fh = path.open(newline="", encoding="utf-8-sig")
    except FileNotFoundError:
        raise _err(sp, "file not found") from None
    except OSError as exc:
        raise _err(sp, f"cannot read ({exc.strerror})") from None
    warnings: list[str] = []
    chunks: list[np.ndarray] = []
    row_lines: list[np.ndarray] | None = None
    n_rows = 0
    line_no = 1
    with fh, tqdm(total=size, desc=f"read {path.name}", unit="B", unit_scale=True, leave=False, disable=None,
                  mininterval=0.5) as bar:
        try:
            first = fh.readline(_MAX_HEADER_CHARS + 1)
            if not first:
                raise _err(sp, "empty file (a header row is required)", 1)
            if len(first) > _MAX_HEADER_CHARS:
                raise _err(sp, f"header row longer than {_MAX_HEADER_CHARS} characters: not a trace header", 1)
            try:
                header = next(csv.reader([first]))
            except (csv.Error, StopIteration) as exc:
                raise _err(sp, f"not a readable CSV header ({exc})", 1) from None
            header = [h.strip() for h in header]
            if header and not set(header) & set(KNOWN_COLUMNS) and all(_is_number(h) for h in header):
                raise _err(sp, f"the first line holds numbers ({first.strip()[:60]}), not column names: the header "
                               f"row is missing (expected names such as {', '.join(KNOWN_COLUMNS[:4])}, ...)", 1)
            if len(set(header)) != len(header):
                dup = next(h for h in header if header.count(h) > 1)
                raise _err(sp, "duplicate column name", 1, dup)
            use = [i for i, h in enumerate(header) if h in KNOWN_COLUMNS]
            names = [header[i] for i in use]
            if not use:
                for sep, what in ((";", "semicolons"), ("\t", "tabs"), ("|", "bars")):
                    if sum(h.strip() in KNOWN_COLUMNS for h in first.rstrip("\r\n").split(sep)) >= 2:
                        raise _err(sp, f"the header is separated by {what}: a trace is comma-separated (CSV with "
                                       "',' between fields and '.' as the decimal point)", 1)
                meant = [h for h in header if _known_column_meant(h)]
                hint = (f"; column names are lower case, without units ({meant[0]!r}: the units are fixed, see "
                        "docs/reference/trace-format.md)" if meant else "")
                raise _err(sp, f"no known column in the header ({', '.join(header)[:200]}); expected "
                               f"{', '.join(KNOWN_COLUMNS)}{hint}", 1)
            bar.update(len(first.encode("utf-8", "replace")))
            line_no = 2
            while True:
                lines = list(islice(fh, _CHUNK_LINES))
                if not lines:
                    break
                nbytes = sum(len(x) for x in lines)
                if not lines[-1].endswith(("\n", "\r")):  # only a file's last line can lack its line end (CR-only
                    # line ends, old Mac style, are line ends too: newline="" splits on them)
                    cut = lines.pop()
                    if cut.strip():
                        warnings.append(f"the last row (line {line_no + len(lines)}) has no line end: the file looks "
                                        "truncated (an interrupted writer?); that row was dropped")
                    if not lines:
                        break
                if line_no == 2 and size > 0 and nbytes > 0:
                    est = int(len(lines) * max(size - len(first), 0) / nbytes)
                    if est > 1.05 * limit:
                        raise _err(sp, f"about {est:,} samples ({size / 2**20:.3g} MiB); the diagnosis reads at most "
                                       f"{limit:,} samples per trace (bounded memory and fit time): cut the trace "
                                       "into segments or decimate it")
                arr = _fast_chunk(lines, len(header), use)
                if arr is None:
                    arr, kept = _careful_chunk(sp, lines, line_no, header, use)
                    if len(kept) != len(lines) and row_lines is None:  # (a blank line: rows and lines part)
                        row_lines = [np.arange(2, n_rows + 2)]
                    if row_lines is not None:
                        row_lines.append(np.asarray(kept, dtype=np.int64))
                elif row_lines is not None:
                    row_lines.append(np.arange(line_no, line_no + len(lines)))
                chunks.append(arr)
                n_rows += arr.shape[0]
                if n_rows > limit:
                    raise _err(sp, f"more than {limit:,} samples; the diagnosis reads at most {limit:,} samples per "
                                   "trace (bounded memory and fit time): cut the trace into segments or decimate it",
                               line_no + len(lines) - 1)
                line_no += len(lines)
                bar.update(nbytes)
        except UnicodeDecodeError:
            bad_line, byte = first_non_utf8_line(path)
            raise _err(sp, f"not UTF-8 text (byte 0x{byte:02x})", bad_line) from None
        except csv.Error as exc:
            raise _err(sp, f"not a readable CSV file ({exc})", line_no) from None
    data = np.concatenate(chunks) if chunks else np.zeros((0, len(names)))
    if not data.shape[0]:
        raise _err(sp, "no data rows")
    return header, names, data, warnings, (np.concatenate(row_lines) if row_lines is not None else None)


#: the top-level keys of a sidecar the diagnosis reads (others are reported as not used)
SIDECAR_KEYS = ("axis", "controller", "notes")


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def read_sidecar(csv_path: Path) -> dict:
    """The optional ``<name>.toml`` metadata beside a trace (axis, controller, notes)."""
    side = csv_path.with_suffix(".toml")
    if not side.exists():
        return {}
    if side.is_dir():
        raise _err(str(side), "sidecar metadata path is a folder, not a TOML file")
    if not side.is_file():
        raise _err(str(side), "sidecar metadata is not a regular file (a device, pipe or socket)")
    try:
        text = read_text_file(side, "sidecar metadata file")
    except ConfigError as exc:
        raise _err(str(side), f"sidecar metadata: {exc.message}") from None
    try:
        return _check_sidecar(side, parse_toml(text))
    except TomlError as exc:
        raise _err(str(side), f"sidecar metadata is {exc}") from None
    except OSError as exc:
        raise _err(str(side), f"cannot read sidecar metadata ({exc.strerror})") from None


def _check_sidecar(side: Path, meta: dict) -> dict:
    """The sidecar is free metadata, but what the reader uses must have its type (``axis`` a name or a table with
    a ``name``), and no number in it may be nan or inf: refused naming the key rather than silently skipped."""
    import math

    ax = meta.get("axis")
    if ax is not None and not isinstance(ax, str) and not (isinstance(ax, dict) and isinstance(ax.get("name"), str)):
        raise _err(str(side), f"key axis: must be the axis name, a string, or a table with a string 'name' (got "
                   f"{ax!r})")

    def walk(key: str, v) -> None:
        if isinstance(v, dict):
            for k, x in v.items():
                walk(f"{key}.{k}" if key else k, x)
        elif isinstance(v, list):
            for i, x in enumerate(v):
                walk(f"{key}[{i}]", x)
        elif isinstance(v, float) and not math.isfinite(v):
            raise _err(str(side), f"key {key}: must be a finite number (got {v!r})")

    walk("", meta)
    return meta


def sidecar_axis_name(meta: dict) -> str | None:
    ax = meta.get("axis")
    if isinstance(ax, str):
        return ax
    if isinstance(ax, dict) and isinstance(ax.get("name"), str):
        return ax["name"]
    return None


def _fill_nans(path: str, name: str, t: np.ndarray, x: np.ndarray, warnings: list[str],
               line: Callable[[int], int] = lambda i: i + 2) -> np.ndarray:
    """``x`` with short runs of missing values interpolated (``line``: the file line of a data row)."""
    bad = ~np.isfinite(x)
    if not bad.any():
        return x
    infinite = np.flatnonzero(np.isinf(x))
    if infinite.size:  # (a number out of range is a corrupted value, not a missing one: not interpolated)
        raise _err(path, f"{x[infinite[0]]} is not a finite number", line(int(infinite[0])), name)
    idx = np.flatnonzero(bad)
    if name in ("t", "pos_cmd") or bad.all():
        raise _err(path, "missing value (NaN or empty)", line(int(idx[0])), name)
    # run lengths
    starts = idx[np.r_[True, np.diff(idx) > 1]]
    ends = idx[np.r_[np.diff(idx) > 1, True]]
    longest = int(np.max(ends - starts + 1))
    if longest > _MAX_NAN_RUN or idx.size > 0.01 * x.size:
        k = int(np.argmax(ends - starts + 1))
        raise _err(
            path,
            f"{idx.size} missing values (NaN or empty), longest run {longest} samples; "
            f"at most {_MAX_NAN_RUN} in a row and 1 % in all are interpolated",
            line(int(starts[k])),
            name,
        )
    good = ~bad
    y = x.copy()
    y[bad] = np.interp(t[bad], t[good], x[good])
    warnings.append(f"{name}: {idx.size} missing values interpolated (first at row {line(int(idx[0]))})")
    return y


#: CiA 402 control and status words, as drive recordings carry them (the live page's): read without a warning,
#: not used
DRIVE_WORDS = frozenset({"statusword", "controlword"})


def simulator_columns() -> frozenset[str]:
    """Every column ``virtualaxis simulate`` writes (with ``--extras``): read without a warning when the
    diagnosis does not use them (``following_error``, ``table_true``, ...)."""
    from virtualaxis.sim.batch import EXTRA_COLUMNS, TRACE_COLUMNS

    return frozenset(TRACE_COLUMNS) | frozenset(EXTRA_COLUMNS)


def read_trace(path: str | Path, axis_name: str | None = None) -> Trace:
    """Read, validate and regularise one trace. ``axis_name``: the config's ``axis.name`` (checked
    against the sidecar metadata)."""
    p = Path(path)
    sp = str(p)
    if p.suffix.lower() == ".npz":  # NPZ: sim.trace_io
        # sizes checked from the archive's directory and the .npy headers before anything is decompressed
        header, data = read_trace_npz(p, max_rows=MAX_TRACE_SAMPLES, columns=KNOWN_COLUMNS)
        names = [h for h in header if h in KNOWN_COLUMNS]
        warnings: list[str] = []
        row_lines = None
    else:
        header, names, data, warnings, row_lines = _parse_csv(p)

    def line(i: int) -> int:
        """The file line of data row ``i`` (blank lines skipped)."""
        return int(row_lines[i]) if row_lines is not None else i + 2

    for col in ("t", "pos_cmd"):
        if col not in header:
            near = next((h for h in header if _known_column_meant(h) == col), None)
            hint = f"; {near!r} is not it: column names are lower case, without units" if near else ""
            raise _err(sp, f"required column '{col}' missing (header: {', '.join(header)}){hint}", 1, col)
    extra = [h for h in header if h not in KNOWN_COLUMNS and h not in simulator_columns() and h not in DRIVE_WORDS]
    for h in extra:  # a measured channel named with its unit would be dropped unseen: refused instead
        meant = _known_column_meant(h)
        if meant is not None and meant not in header:
            raise _err(sp, f"column {h!r} is not a trace column; {meant!r} is (column names are lower case, without "
                           "units: every column is in SI units, docs/reference/trace-format.md)", 1, h)
    if not any(c in header for c in POSITION_COLUMNS):
        raise _err(sp, "needs at least one of the columns pos_meas, pos_fb, motor_pos", 1)
    if data.shape[0] < 16:
        raise _err(sp, f"only {data.shape[0]} data row{'s' if data.shape[0] != 1 else ''} (at least 16 needed)")
    cols = {h: data[:, i] for i, h in enumerate(names)}
    if any(extra):
        warnings.append(f"extra columns ignored: {', '.join(h for h in extra if h)}")
    if "" in extra:
        warnings.append("a column without a name ignored (a trailing comma in the header?)")
    t = cols["t"]
    _fill_nans(sp, "t", t, t, warnings, line)
    dt = np.diff(t)
    nonmono = np.flatnonzero(dt <= 0)
    if nonmono.size:
        i = int(nonmono[0]) + 1
        raise _err(sp, f"time is not increasing ({float(t[i - 1])!r} then {float(t[i])!r})", line(i), "t")
    dt_med = float(np.median(dt))
    check_sample_interval(sp, dt_med)
    quantum = float(np.spacing(max(abs(float(t[0])), abs(float(t[-1])))))
    if quantum > 1e-5 * dt_med:  # epoch time stamps: the double has lost the sub-sample time before we read it
        raise _err(sp, f"time stamps reach {max(abs(float(t[0])), abs(float(t[-1]))):.6g} s, where a number resolves "
                       f"only {quantum:.2g} s ({quantum / dt_med:.1e} of the {dt_med:.3g} s sample interval; it would "
                       "look like jitter and be resampled): subtract the start time (epoch time stamps?)", 2, "t")
    gaps = np.flatnonzero(dt > _GAP_FACTOR * dt_med)
    if gaps.size:
        i = int(gaps[0]) + 1
        raise _err(
            sp,
            f"time gap of {dt[i - 1]:.6g} s (sample period {dt_med:.6g} s) between rows {line(i - 1)} and "
            f"{line(i)}",
            line(i),
            "t",
        )
    for name in list(cols):
        if name != "t":
            cols[name] = _fill_nans(sp, name, t, cols[name], warnings, line)
    check_wraps(sp, cols, line)  # (before any resampling blurs a wrap into a fast swing)
    meta = read_sidecar(p)
    side_axis = sidecar_axis_name(meta)
    if axis_name and side_axis and side_axis != axis_name:
        raise _err(
            str(p.with_suffix(".toml")),
            f"key axis: the trace belongs to axis '{side_axis}', the config is for axis '{axis_name}'",
        )
    unused = [k for k in meta if k not in SIDECAR_KEYS]
    if unused:
        warnings.append(f"{p.with_suffix('.toml')}: sidecar key(s) not used: {', '.join(unused)} (the diagnosis "
                        f"reads {', '.join(SIDECAR_KEYS)}; see docs/reference/trace-format.md)")
    jitter = float(np.max(np.abs(dt - dt_med))) / dt_med
    if jitter > _JITTER_TOLERANCE:
        n = int(round((t[-1] - t[0]) / dt_med)) + 1
        tu = t[0] + dt_med * np.arange(n)
        tu = tu[tu <= t[-1] + 1e-12 * abs(t[-1])]
        for name in list(cols):
            if name != "t":
                cols[name] = np.interp(tu, t, cols[name])
        warnings.append(
            f"time jitter up to {100 * jitter:.2g} % of the {dt_med * 1e3:.4g} ms period: "
            f"resampled linearly onto a uniform grid ({tu.size} samples)"
        )
        t = tu
    cols["t"] = t
    columns = {k: v for k, v in cols.items() if k != "t"}
    tr = Trace(name=p.stem, path=sp, t=t - t[0], columns=columns, metadata=meta, warnings=warnings)
    tr.metadata.setdefault("t0_s", float(t[0]))
    return tr


#: sample intervals of drive traces [s]: 1 us (current-loop recorders) .. 0.1 s (slow loggers)
DT_RANGE_S = (1e-6, 0.1)


def check_sample_interval(path: str, dt_s: float) -> None:
    """The time unit from the sampling interval: a drive trace samples every 1 us .. 0.1 s. A 1 s interval is
    ``t`` in milliseconds written as seconds (or a logger far too slow for servo dynamics)."""
    lo, hi = DT_RANGE_S
    if not lo <= dt_s <= hi:
        hint = " (is t in milliseconds? it must be in seconds)" if dt_s > hi else " (is t in seconds?)"
        raise _err(path, f"sample interval {dt_s:g} s is outside {lo:g} .. {hi:g} s of a drive trace{hint}", 3, "t")


def _first_row(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0]) + 2


def check_units(trace: Trace, cfg) -> None:
    """Unit and plausibility checks against the axis config. Raises InputError for values that are
    clearly in the wrong unit or from another axis; records milder findings as warnings."""
    sp = trace.path
    stroke = float(cfg.axis.stroke_m)
    travel = max(abs(cfg.limits.travel_min_m), abs(cfg.limits.travel_max_m))
    pos_limit = max(2.0 * stroke, 1.0) if travel > 1e6 else max(2.0 * travel, 2.0 * stroke)
    cmd = trace.pos_cmd
    for col in ("pos_cmd", "pos_meas", "pos_fb"):
        x = trace.columns.get(col)
        if x is None:
            continue
        bad = np.abs(x) > pos_limit
        if bad.any():
            v = float(x[np.flatnonzero(bad)[0]])
            raise _err(
                sp,
                f"position {v:g} m is not plausible for axis '{cfg.axis.name}' (stroke {stroke:g} m); "
                "positions must be in metres (is it mm?)",
                _first_row(bad),
                col,
            )
    span = float(np.ptp(cmd))
    if span > 0:
        for col in ("pos_meas", "pos_fb"):
            x = trace.columns.get(col)
            if x is None:
                continue
            ratio = float(np.ptp(x)) / span
            if not 0.5 < ratio < 2.0:
                raise _err(
                    sp,
                    f"travels {ratio:.3g} times as far as pos_cmd: not the same unit or not the same axis",
                    None,
                    col,
                )
        mp = trace.columns.get("motor_pos")
        if mp is not None:
            lead = cfg.mechanics.lead_m
            if lead > 0:
                expect = 2 * math.pi / lead
                # against a measured position where there is one: the command leads the motion by the loop's lag,
                # which on a short trace from rest is a large share of the travel
                ref_col = next((c for c in ("pos_fb", "pos_meas") if c in trace.columns
                                and float(np.ptp(trace.columns[c])) > 0.5 * span), "pos_cmd")
                slope = float(np.polyfit(trace.columns[ref_col], mp, 1)[0])
                if not 0.8 < abs(slope) / expect < 1.25:
                    raise _err(
                        sp,
                        f"motor_pos turns {abs(slope):.4g} rad per metre of {ref_col}, the config's lead "
                        f"{lead:g} m gives {expect:.4g} rad/m: motor_pos must be in rad, or the trace is "
                        "from another axis",
                        None,
                        "motor_pos",
                    )
                if float(np.polyfit(cmd, mp, 1)[0]) < 0:  # (the direction against the command itself)
                    trace.warnings.append("motor_pos turns negatively with pos_cmd: sign flipped")
                    trace.columns["motor_pos"] = -mp
    vmax_cmd = trace.max_speed_m_s()
    if vmax_cmd > 3.0 * cfg.limits.max_velocity_m_s:
        raise _err(
            sp,
            f"command speed {vmax_cmd:.3g} m/s is over 3 x the axis limit {cfg.limits.max_velocity_m_s:g} m/s"
            " (wrong time unit, or a trace of another axis)",
            None,
            "pos_cmd",
        )
    vel = trace.columns.get("vel_meas")
    if vel is not None and vmax_cmd > 0:
        ratio = float(np.max(np.abs(vel))) / vmax_cmd
        if ratio > 20 or ratio < 0.05:
            raise _err(sp, f"peaks at {ratio:.3g} times the command speed: not in m/s", None, "vel_meas")
    tq = trace.columns.get("torque_meas")
    if tq is not None and cfg.actuator.kind == "pmsm":
        ref = cfg.motor.rated_torque_nm or cfg.motor.rated_current_a * max(cfg.motor.torque_constant_nm_per_a, 0.1)
        bad = np.abs(tq) > 20 * ref
        if bad.any():
            raise _err(
                sp, f"torque {float(tq[bad][0]):g} N m is over 20 x the rated torque {ref:g} N m (unit?)",
                _first_row(bad), "torque_meas",
            )
    iq = trace.columns.get("current_q")
    if iq is not None:
        bad = np.abs(iq) > 20 * cfg.motor.rated_current_a
        if bad.any():
            raise _err(
                sp, f"current {float(iq[bad][0]):g} A is over 20 x the rated current (unit?)", _first_row(bad),
                "current_q",
            )


#: channels that a recorder may have held in a fixed-width integer (counts scaled to SI): a value that overflowed
#: it wraps to the other end of its range (the motor angle is left out: an angle may wrap by design)
WRAP_CHANNELS = ("current_q", "torque_meas", "force_drive", "vel_meas")
#: unwrapped, the channel's largest step must be below this share of its range (a continuous signal) ...
WRAP_SMOOTH_SHARE = 0.25
#: ... and it must reach beyond the recorded range by more than this share of the range (values that did not fit)
WRAP_BEYOND_SHARE = 0.05


def check_wraps(path: str, columns: dict[str, np.ndarray], line: Callable[[int], int]) -> None:
    """A channel whose value wrapped around the integer range it was recorded in (a 16-bit current counter that
    overflowed: +32767 mA, then -32768 mA) is refused, naming the row: taken as it stands, a wrapped sample is a
    full-range spike that no model follows.

    The test unwraps the channel with its range as the period (a step of more than half the range is carried
    across it, as ``numpy.unwrap`` does): a wrapped channel comes out continuous (every step below
    :data:`WRAP_SMOOTH_SHARE` of the range) and reaches beyond the range it was recorded in (by more than
    :data:`WRAP_BEYOND_SHARE` of it). A current that switches between two levels (a torque square wave) comes out
    as one level within its range, a spike as a dip within it: no wrap. A channel whose noise alone moves it by
    half its range from one sample to the next cannot be told apart and passes."""
    for col in WRAP_CHANNELS:
        x = columns.get(col)
        if x is None or x.size < 8:
            continue
        lo, hi = float(np.min(x)), float(np.max(x))
        d = np.diff(x)
        width = (hi - lo) + float(np.median(np.abs(d)))  # the range the values wrap in: lowest to highest + a step
        if not width > 0.0 or not np.any(np.abs(d) > 0.5 * width):
            continue
        u = np.unwrap(x, period=width)
        if float(np.max(np.abs(np.diff(u)))) >= WRAP_SMOOTH_SHARE * width:
            continue
        beyond = max(float(np.max(u)) - hi, lo - float(np.min(u)))
        if beyond <= WRAP_BEYOND_SHARE * width:
            continue
        i = int(np.flatnonzero(np.abs(d) > 0.5 * width)[0])
        unit = CHANNEL_UNITS.get(col, "")
        raise _err(
            path,
            f"jumps from {float(x[i]):.6g} to {float(x[i + 1]):.6g} {unit} between two samples, across its whole "
            f"range ({lo:.6g} .. {hi:.6g} {unit}), and runs on smoothly beyond that range once carried across it "
            f"(by up to {beyond:.3g} {unit}): the value wrapped around the integer range it was recorded in "
            "(a 16-bit counter?); record it in a wider type, or unwrap it",
            line(i + 1),
            col,
        )


def write_trace(path: str | Path, columns: dict[str, np.ndarray], order: tuple[str, ...] = KNOWN_COLUMNS) -> None:
    """Write a trace CSV (used by the gap bench). Columns that are all-NaN are left out."""
    names = [c for c in order if c in columns and np.isfinite(np.asarray(columns[c])).any()]
    data = np.column_stack([np.asarray(columns[c], dtype=float) for c in names])
    with Path(path).open("w", encoding="utf-8", newline="") as fh:
        fh.write(",".join(names) + "\n")
        np.savetxt(fh, data, delimiter=",", fmt="%.10g")
