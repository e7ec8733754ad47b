"""Start values of the candidate effects: the resonance frequency is scanned, not taken from one peak."""

from __future__ import annotations

import math

from virtualaxis.config import load_axis_config
from virtualaxis.diagnosis.bench import BALLSCREW_CONFIG
from virtualaxis.diagnosis.effects import EFFECTS


def _freqs(hints: dict) -> list[float]:
    cfg = load_axis_config(BALLSCREW_CONFIG)
    return [s["resonance_frequency_hz"] for s in EFFECTS["resonance"].starts(cfg, hints)]


def test_resonance_starts_cover_the_band_without_hints():
    f = sorted(_freqs({}))
    assert f[0] <= 5.0 and f[-1] >= 200.0
    # neighbouring start frequencies at most 1.3x apart: a mode anywhere in 5..200 Hz is within 15 %
    assert max(b / a for a, b in zip(f, f[1:], strict=False)) <= 1.3 + 1e-9


def test_resonance_starts_put_spectral_peaks_of_every_channel_first_and_drop_near_duplicates():
    f = _freqs({"peaks_hz": [107.0], "peaks_all_hz": [184.5, 108.0, 45.0]})
    assert f[:3] == [107.0, 184.5, 45.0]  # 108 Hz is within 8 % of 107 Hz: dropped
    assert all(max(a, b) / min(a, b) >= 1.08 for i, a in enumerate(f) for b in f[i + 1:])
    assert all(3.0 <= x <= 400.0 for x in f) and not any(math.isnan(x) for x in f)
