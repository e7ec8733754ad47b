"""Where the gap lies: residual energy shares by motion phase, direction, speed, stroke position,
time within the trace, trace and frequency band, in every measured channel.

The residual is ``measured - simulated`` per channel. Each sample is labelled from the *command*
(so the labels do not depend on the model being right): motion phase (standstill, acceleration,
constant velocity, reversal), direction, speed bin, stroke-position bin and time quarter. A bin's
``share`` is its part of the channel's residual energy (sum of squares); ``time_fraction`` is its
part of the samples, so ``share / time_fraction`` > 1 means the gap concentrates there. Frequency
shares come from Welch spectra of the residual; coherence with the command says how much of the
residual in a band is linearly explained by the command.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal

PHASES = ("standstill", "acceleration", "constant_velocity", "reversal")
FREQ_EDGES_HZ = (0.0, 1.0, 5.0, 20.0, 100.0)
SPEED_FRACTIONS = (0.0, 0.1, 0.4, 0.7, 1.0001)
N_POSITION_BINS = 5
N_TIME_BINS = 4
#: half-width of the window around a direction change labelled "reversal" [s]
REVERSAL_HALF_WINDOW_S = 0.05


@dataclass
class MotionScale:
    """Global scales over all traces of a data set, so bins mean the same in every trace."""

    vmax_m_s: float
    amax_m_s2: float
    pos_min_m: float
    pos_max_m: float

    @classmethod
    def from_commands(cls, items: list[tuple[np.ndarray, np.ndarray]]) -> MotionScale:
        vmax = amax = 0.0
        lo, hi = np.inf, -np.inf
        for t, cmd in items:
            v, a = command_derivatives(t, cmd)
            vmax = max(vmax, float(np.max(np.abs(v))))
            amax = max(amax, float(np.max(np.abs(a))))
            lo, hi = min(lo, float(cmd.min())), max(hi, float(cmd.max()))
        return cls(max(vmax, 1e-9), max(amax, 1e-9), lo, hi if hi > lo else lo + 1e-9)


def _smooth(x: np.ndarray, n: int) -> np.ndarray:
    if n <= 1 or x.size < 3 * n:
        return x
    k = np.ones(n) / n
    return np.convolve(np.pad(x, (n // 2, n - 1 - n // 2), mode="edge"), k, mode="valid")


def command_derivatives(t: np.ndarray, cmd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Command velocity [m/s] and acceleration [m/s^2], lightly smoothed (5 ms)."""
    dt = float(t[1] - t[0])
    n = max(1, int(round(0.005 / dt)))
    v = _smooth(np.gradient(cmd, dt), n)
    a = _smooth(np.gradient(v, dt), n)
    return v, a


def motion_labels(t: np.ndarray, cmd: np.ndarray, scale: MotionScale) -> dict[str, np.ndarray]:
    """Per-sample bin labels (integer codes) for each dimension; see :func:`bin_names`."""
    v, a = command_derivatives(t, cmd)
    dt = float(t[1] - t[0])
    v_eps = 0.01 * scale.vmax_m_s
    moving = np.abs(v) > v_eps
    sgn = np.where(moving, np.sign(v), 0.0)
    phase = np.full(t.size, 2, dtype=np.int8)  # constant velocity
    phase[np.abs(a) > 0.2 * scale.amax_m_s2] = 1
    phase[~moving] = 0
    # reversal: around each change of the direction of motion (also across a dwell)
    w = max(1, int(round(REVERSAL_HALF_WINDOW_S / dt)))
    idx = np.flatnonzero(moving)
    if idx.size > 1:
        s = sgn[idx]
        change = np.flatnonzero(s[1:] != s[:-1])
        for c in change:
            i0, i1 = idx[c], idx[c + 1]
            if (i1 - i0) * dt > 4 * REVERSAL_HALF_WINDOW_S:  # long dwell: only the move starts/ends
                phase[max(0, i0 - w) : i0 + 1] = 3
                phase[i1 : i1 + w + 1] = 3
            else:
                phase[max(0, i0 - w) : i1 + w + 1] = 3
    direction = np.where(sgn > 0, 0, np.where(sgn < 0, 1, 2)).astype(np.int8)
    frac = np.abs(v) / scale.vmax_m_s
    speed = (np.searchsorted(np.asarray(SPEED_FRACTIONS), frac, side="right") - 1).clip(0, len(SPEED_FRACTIONS) - 2)
    rel = (cmd - scale.pos_min_m) / (scale.pos_max_m - scale.pos_min_m)
    position = np.clip((rel * N_POSITION_BINS).astype(int), 0, N_POSITION_BINS - 1)
    tq = (t - t[0]) / max(float(t[-1] - t[0]), 1e-12)
    time = np.clip((tq * N_TIME_BINS).astype(int), 0, N_TIME_BINS - 1)
    return {"phase": phase, "direction": direction, "speed": speed, "position": position, "time": time}


def bin_names(scale: MotionScale) -> dict[str, list[str]]:
    sp = [
        f"{SPEED_FRACTIONS[i] * scale.vmax_m_s * 6e4:.0f}-{min(SPEED_FRACTIONS[i + 1], 1) * scale.vmax_m_s * 6e4:.0f}"
        " mm/min"
        for i in range(len(SPEED_FRACTIONS) - 1)
    ]
    step = (scale.pos_max_m - scale.pos_min_m) / N_POSITION_BINS
    pos = [
        f"{(scale.pos_min_m + i * step) * 1e3:.1f}..{(scale.pos_min_m + (i + 1) * step) * 1e3:.1f} mm"
        for i in range(N_POSITION_BINS)
    ]
    return {
        "phase": list(PHASES),
        "direction": ["positive", "negative", "standstill"],
        "speed": sp,
        "position": pos,
        "time": [f"quarter {i + 1}" for i in range(N_TIME_BINS)],
    }


def band_names(fs_hz: float) -> list[str]:
    edges = [e for e in FREQ_EDGES_HZ if e < fs_hz / 2] + [fs_hz / 2]
    return [f"{edges[i]:g}-{edges[i + 1]:g} Hz" for i in range(len(edges) - 1)]


def _band_energy(f: np.ndarray, p: np.ndarray, fs_hz: float) -> np.ndarray:
    edges = [e for e in FREQ_EDGES_HZ if e < fs_hz / 2] + [fs_hz / 2 + 1e-9]
    out = np.zeros(len(edges) - 1)
    for i in range(len(edges) - 1):
        m = (f >= edges[i]) & (f < edges[i + 1])
        out[i] = float(np.sum(p[m]))
    return out


def spectrum(t: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    fs = 1.0 / float(t[1] - t[0])
    nper = int(min(x.size, max(256, 2 ** int(np.log2(max(x.size // 4, 1))))))
    return signal.welch(x - np.mean(x), fs=fs, nperseg=nper)


@dataclass
class Localisation:
    """Result of :func:`localise`."""

    entries: list[dict]  # {"channel","dimension","bin","share","time_fraction"}
    spectra: dict  # channel -> {"f_hz": [...], "psd": [...], "peak_hz": float, "coherence": {...}}
    scale: MotionScale

    def shares(self, channel: str, dimension: str) -> dict[str, float]:
        return {
            e["bin"]: e["share"] for e in self.entries if e["channel"] == channel and e["dimension"] == dimension
        }

    def vector(self, channel: str) -> np.ndarray:
        """All shares of a channel in a fixed order (for signature comparison)."""
        return np.array([e["share"] for e in self.entries if e["channel"] == channel])

    def concentrations(self, channel: str, min_ratio: float = 1.5) -> list[dict]:
        """Bins holding a markedly larger share of the energy than of the samples."""
        out = []
        for e in self.entries:
            if e["channel"] != channel or e["dimension"] in ("frequency", "trace"):
                continue
            if e["time_fraction"] > 0.01 and e["share"] / e["time_fraction"] >= min_ratio:
                out.append(e)
        return sorted(out, key=lambda e: -e["share"] / e["time_fraction"])


def localise(
    items: list[tuple[str, np.ndarray, np.ndarray, dict[str, np.ndarray]]],
    scale: MotionScale | None = None,
) -> Localisation:
    """Residual energy shares.

    ``items``: per trace ``(name, t_s, pos_cmd_m, {channel: residual})``; residuals in channel units.
    """
    if scale is None:
        scale = MotionScale.from_commands([(t, c) for _, t, c, _ in items])
    names = bin_names(scale)
    channels: list[str] = []
    for _, _, _, res in items:
        for ch in res:
            if ch not in channels:
                channels.append(ch)
    entries: list[dict] = []
    spectra: dict = {}
    labels = [motion_labels(t, cmd, scale) for _, t, cmd, _ in items]
    n_total = sum(t.size for _, t, _, _ in items)
    for ch in channels:
        total = sum(float(np.sum(res[ch] ** 2)) for _, _, _, res in items if ch in res)
        n_ch = sum(t.size for _, t, _, res in items if ch in res)
        total = max(total, 1e-300)
        for dim, bins in names.items():
            e_bin = np.zeros(len(bins))
            n_bin = np.zeros(len(bins))
            for (_, _, _, res), lab in zip(items, labels, strict=True):
                if ch not in res:
                    continue
                r2 = res[ch] ** 2
                e_bin += np.bincount(lab[dim], weights=r2, minlength=len(bins))[: len(bins)]
                n_bin += np.bincount(lab[dim], minlength=len(bins))[: len(bins)]
            for b, name in enumerate(bins):
                entries.append(
                    {"channel": ch, "dimension": dim, "bin": name, "share": float(e_bin[b] / total),
                     "time_fraction": float(n_bin[b] / max(n_ch, 1))}
                )
        for name, t, _, res in items:
            if ch in res:
                entries.append(
                    {"channel": ch, "dimension": "trace", "bin": name,
                     "share": float(np.sum(res[ch] ** 2) / total), "time_fraction": float(t.size / n_total)}
                )
        # frequency
        fs = 1.0 / float(items[0][1][1] - items[0][1][0])
        bands = band_names(fs)
        e_band = np.zeros(len(bands))
        coh_w = np.zeros(len(bands))
        psd_sum = None
        f_ref = None
        for _, t, cmd, res in items:
            if ch not in res or t.size < 64:
                continue
            f, p = spectrum(t, res[ch])
            e = _band_energy(f, p, 1.0 / float(t[1] - t[0]))
            if e.size == e_band.size:
                e_band += e
                nper = min(res[ch].size, 1024)
                with np.errstate(invalid="ignore", divide="ignore"):
                    fc, cxy = signal.coherence(cmd - cmd.mean(), res[ch] - res[ch].mean(), fs=fs, nperseg=nper)
                pc = np.interp(fc, f, p)
                coh_w += _band_energy(fc, np.nan_to_num(cxy) * pc, fs)
            if f_ref is None:
                f_ref, psd_sum = f, p.copy()
            elif f.size == f_ref.size:
                psd_sum += p
        tot_band = max(float(e_band.sum()), 1e-300)
        for b, name in enumerate(bands):
            entries.append(
                {"channel": ch, "dimension": "frequency", "bin": name, "share": float(e_band[b] / tot_band),
                 "time_fraction": float("nan")}
            )
        if f_ref is not None:
            m = f_ref > 2.0
            peak = float(f_ref[m][np.argmax(psd_sum[m])]) if m.any() else float("nan")
            e_band_safe = np.where(e_band > 0, e_band, 1.0)
            spectra[ch] = {
                "f_hz": f_ref.tolist(),
                "psd": psd_sum.tolist(),
                "peak_hz_above_2hz": peak,
                "coherence_with_command": {bands[b]: float(coh_w[b] / e_band_safe[b]) for b in range(len(bands))},
            }
    return Localisation(entries=entries, spectra=spectra, scale=scale)


def signature_overlap(a: Localisation, b: Localisation, channel: str) -> float:
    """Bhattacharyya overlap (0..1) of two localisations of one channel, averaged over the dimensions:
    1 = the energy lies in the same bins, 0 = in disjoint bins."""
    dims = ("phase", "direction", "speed", "position", "time", "frequency")
    vals = []
    for d in dims:
        pa, pb = a.shares(channel, d), b.shares(channel, d)
        if not pa or not pb:
            continue
        keys = [k for k in pa if k in pb]
        sa = np.array([max(pa[k], 0.0) for k in keys])
        sb = np.array([max(pb[k], 0.0) for k in keys])
        if sa.sum() <= 0 or sb.sum() <= 0:
            continue
        vals.append(float(np.sum(np.sqrt(sa / sa.sum() * sb / sb.sum()))))
    return float(np.mean(vals)) if vals else float("nan")
