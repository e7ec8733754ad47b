"""Measured data for the identification: FRF CSV files and natural-frequency tables (docs/rcsa.md).

FRF CSV: a header row, then one row per sample with columns ``position_m, freq_hz`` and either
``re, im`` [m/N] or ``mag, phase_deg`` ([m/N], degrees). Within each position the frequencies must be
strictly increasing (no duplicates), every value finite.

Mode-table CSV (what the paper prints in Tables 1/2/4): columns ``position_m, order, freq_hz`` and
optionally ``amplitude_m_per_n``; an empty cell (or ``-``/``—``) is a gap.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from virtualaxis.config.errors import InputError
from virtualaxis.rcsa.identify import MeasuredModes
from virtualaxis.rcsa.params import RcsaModel
from virtualaxis.rcsa.peaks import measured_modes
from virtualaxis.rcsa.receptance import table_frf

FRF_COLUMNS_COMPLEX = ("position_m", "freq_hz", "re", "im")
FRF_COLUMNS_POLAR = ("position_m", "freq_hz", "mag", "phase_deg")
MODE_TABLE_COLUMNS = ("position_m", "order", "freq_hz")
_GAP = ("", "-", "—")  # an explicit gap; "nan" is refused as an error


@dataclass(frozen=True)
class MeasuredFrf:
    """One measured table FRF h_6a6a at one worktable position."""

    position_m: float
    freq_hz: np.ndarray
    h_m_per_n: np.ndarray


def _float(file: str, row: int, col: str, text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise InputError(file, f"not a number: {text!r}", row=row, column=col) from None
    if not math.isfinite(v):
        raise InputError(file, f"not a finite number: {text!r}", row=row, column=col)
    return v


def _read_rows(path: str | Path) -> tuple[str, list[str], list[tuple[int, list[str]]]]:
    file = str(path)
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            lines = [
                (i + 1, r) for i, r in enumerate(csv.reader(fh)) if r and not r[0].lstrip().startswith("#")
            ]
    except FileNotFoundError:
        raise InputError(file, "file not found") from None
    except UnicodeDecodeError:
        raise InputError(file, "not a UTF-8 text file") from None
    if not lines:
        raise InputError(file, "empty file (expected a header row)")
    header = [h.strip() for h in lines[0][1]]
    return file, header, lines[1:]


def read_frf_csv(path: str | Path) -> list[MeasuredFrf]:
    """Read an FRF CSV (complex or polar). Raises :class:`InputError` naming file, row and column."""
    file, header, rows = _read_rows(path)
    if set(FRF_COLUMNS_COMPLEX) <= set(header):
        cols, polar = FRF_COLUMNS_COMPLEX, False
    elif set(FRF_COLUMNS_POLAR) <= set(header):
        cols, polar = FRF_COLUMNS_POLAR, True
    else:
        raise InputError(
            file,
            f"header must hold {', '.join(FRF_COLUMNS_COMPLEX)} or {', '.join(FRF_COLUMNS_POLAR)}"
            f" (got {', '.join(header)})",
            row=1,
        )
    idx = [header.index(c) for c in cols]
    if not rows:
        raise InputError(file, "no data rows")
    data: dict[float, list[tuple[int, float, complex]]] = {}
    for line_no, r in rows:
        if len(r) < len(header):
            raise InputError(file, f"expected {len(header)} columns, got {len(r)}", row=line_no)
        pos, f, a, b = (_float(file, line_no, c, r[i].strip()) for c, i in zip(cols, idx, strict=True))
        if f <= 0:
            raise InputError(file, f"frequency must be > 0 (got {f})", row=line_no, column="freq_hz")
        if polar:
            if a < 0:
                raise InputError(file, f"magnitude must be >= 0 (got {a})", row=line_no, column="mag")
            h = a * complex(math.cos(math.radians(b)), math.sin(math.radians(b)))
        else:
            h = complex(a, b)
        data.setdefault(round(pos, 9), []).append((line_no, f, h))
    out = []
    for pos, samples in data.items():
        freqs = np.array([s[1] for s in samples])
        bad = np.nonzero(np.diff(freqs) <= 0)[0]
        if bad.size:
            k = int(bad[0]) + 1
            what = "duplicate" if freqs[k] == freqs[k - 1] else "unsorted (decreasing)"
            raise InputError(
                file,
                f"{what} frequency {freqs[k]:g} Hz at position {pos:g} m",
                row=samples[k][0],
                column="freq_hz",
            )
        if freqs.size < 3:
            raise InputError(file, f"position {pos:g} m has fewer than 3 samples", row=samples[0][0])
        out.append(MeasuredFrf(pos, freqs, np.array([s[2] for s in samples])))
    out.sort(key=lambda m: m.position_m)
    return out


def write_frf_csv(path: str | Path, frfs: list[MeasuredFrf]) -> None:
    """Write FRFs in the complex CSV format read by :func:`read_frf_csv`."""
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(FRF_COLUMNS_COMPLEX)
        for m in frfs:
            for f, h in zip(m.freq_hz, m.h_m_per_n, strict=True):
                w.writerow([repr(m.position_m), repr(float(f)), repr(float(h.real)), repr(float(h.imag))])


def read_mode_table_csv(path: str | Path, n_modes: int) -> MeasuredModes:
    """Read a natural-frequency table (position_m, order, freq_hz[, amplitude_m_per_n]); orders 1..n_modes."""
    file, header, rows = _read_rows(path)
    missing = [c for c in MODE_TABLE_COLUMNS if c not in header]
    if missing:
        raise InputError(file, f"missing column(s) {', '.join(missing)} in the header", row=1)
    has_amp = "amplitude_m_per_n" in header
    table: dict[float, tuple[np.ndarray, np.ndarray]] = {}
    for line_no, r in rows:
        if len(r) < len(header):
            raise InputError(file, f"expected {len(header)} columns, got {len(r)}", row=line_no)
        cell = {c: r[header.index(c)].strip() for c in header}
        pos = _float(file, line_no, "position_m", cell["position_m"])
        order_f = _float(file, line_no, "order", cell["order"])
        if not order_f.is_integer() or not 1 <= order_f <= n_modes:
            raise InputError(file, f"order must be an integer 1..{n_modes}", row=line_no, column="order")
        order = int(order_f) - 1
        freqs, amps = table.setdefault(round(pos, 9), (np.full(n_modes, np.nan), np.full(n_modes, np.nan)))
        if not math.isnan(freqs[order]):
            raise InputError(
                file, f"duplicate order {order + 1} at position {pos:g} m", row=line_no, column="order"
            )
        if cell["freq_hz"] not in _GAP:
            f = _float(file, line_no, "freq_hz", cell["freq_hz"])
            if f <= 0:
                raise InputError(file, f"frequency must be > 0 (got {f})", row=line_no, column="freq_hz")
            freqs[order] = f
        if has_amp and cell["amplitude_m_per_n"] not in _GAP:
            a = _float(file, line_no, "amplitude_m_per_n", cell["amplitude_m_per_n"])
            if a <= 0:
                raise InputError(
                    file, f"amplitude must be > 0 (got {a})", row=line_no, column="amplitude_m_per_n"
                )
            amps[order] = a
    if not table:
        raise InputError(file, "no data rows")
    positions = np.array(sorted(table))
    for pos in positions:
        freqs = table[pos][0]
        present = freqs[np.isfinite(freqs)]
        if np.any(np.diff(present) <= 0):
            raise InputError(file, f"natural frequencies at position {pos:g} m must increase with the order")
    return MeasuredModes(
        positions,
        np.array([table[p][0] for p in positions]),
        np.array([table[p][1] for p in positions]),
    )


def modes_from_frfs(frfs: list[MeasuredFrf], model: RcsaModel) -> MeasuredModes:
    """Extract natural frequency and peak amplitude per mode band from each measured FRF (NaN = gap)."""
    bands = model.bands_array()
    freqs, amps = [], []
    for m in frfs:
        f, a = measured_modes(m.freq_hz, np.abs(m.h_m_per_n), bands, model.min_peak_prominence)
        freqs.append(f)
        amps.append(a)
    return MeasuredModes(np.array([m.position_m for m in frfs]), np.array(freqs), np.array(amps))


def synthetic_frfs(
    model: RcsaModel,
    positions_m: list[float],
    freq_hz: np.ndarray,
    *,
    magnitude_noise: float = 0.02,
    phase_noise_deg: float = 1.0,
    noise_floor_m_per_n: float = 1e-12,
    seed: int = 0,
) -> list[MeasuredFrf]:
    """'Measured' FRFs from the model with its joints plus hammer-test-like noise: multiplicative
    magnitude noise (relative std), phase noise (std, degrees) and an additive complex noise floor."""
    rng = np.random.default_rng(seed)
    p = model.parameter_vector()
    out = []
    for pos in positions_m:
        model.check_position(pos)
        h = np.empty(freq_hz.size, dtype=np.complex128)
        table_frf(np.ascontiguousarray(freq_hz, dtype=np.float64), float(pos), p, h)
        gain = (1.0 + magnitude_noise * rng.standard_normal(h.size)) * np.exp(
            1j * np.radians(phase_noise_deg) * rng.standard_normal(h.size)
        )
        floor = noise_floor_m_per_n * (rng.standard_normal(h.size) + 1j * rng.standard_normal(h.size))
        out.append(MeasuredFrf(float(pos), freq_hz.copy(), h * gain + floor))
    return out
