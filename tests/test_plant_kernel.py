"""The kernel's speed paths compute what the plain formulas compute, to round-off: the vectorised 12-state
zero-order-hold step, the sine/cosine rotation recurrence, and the Stribeck cut-off."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numba import njit

from virtualaxis.sim.kernel import SIN_STEP_MAX_RAD, _zoh_12, _zoh_generic, sin_cos_step, stribeck_cut_ratio

# not cached: numba's cache would not notice a change in the kernel functions these wrappers inline


@njit
def _step_12(at, bt, m, z, u):
    _zoh_12(at, bt, m, z, u[0], u[1], u[2], u[3])


@njit
def _step_generic(at, bt, m, z, ztmp, u):
    _zoh_generic(at, bt, m, z, ztmp, z.shape[0], u[0], u[1], u[2], u[3])


@njit
def _recurrence(xs, reseed_every):
    out = np.empty((xs.shape[0], 2))
    xp, sp, cp = 0.0, 0.0, 1.0
    for k in range(xs.shape[0]):
        sp, cp = sin_cos_step(xs[k], xp, sp, cp, k % reseed_every == 0)
        xp = xs[k]
        out[k, 0] = sp
        out[k, 1] = cp
    return out


def test_zoh_12_equals_the_matrix_product_for_every_mode():
    rng = np.random.default_rng(7)
    ad = rng.standard_normal((4, 12, 12))
    bd = rng.standard_normal((4, 12, 4))
    at = np.ascontiguousarray(np.swapaxes(ad, 1, 2))
    bt = np.ascontiguousarray(np.swapaxes(bd, 1, 2))
    u = rng.standard_normal(4)
    for m in range(4):
        z0 = rng.standard_normal(12)
        expected = ad[m] @ z0 + bd[m] @ u
        st = np.zeros(52)
        st[40:] = z0
        _step_12(at, bt, m, st[40:], u)  # a view into a larger array, as the kernel passes it
        assert np.all(st[:40] == 0.0)
        np.testing.assert_allclose(st[40:], expected, rtol=0, atol=1e-13 * np.max(np.abs(expected)))
        z = z0.copy()
        _step_generic(at, bt, m, z, np.zeros(12), u)
        np.testing.assert_allclose(z, expected, rtol=0, atol=1e-13 * np.max(np.abs(expected)))


@pytest.mark.parametrize("max_step", [1e-5, 0.03, SIN_STEP_MAX_RAD, 0.5])
def test_sin_cos_recurrence_matches_libm_to_round_off(max_step):
    rng = np.random.default_rng(3)
    xs = 950.0 + np.cumsum(rng.uniform(-max_step, max_step, 20000))
    got = _recurrence(xs, 32)
    assert np.max(np.abs(got[:, 0] - np.sin(xs))) < 2e-15
    assert np.max(np.abs(got[:, 1] - np.cos(xs))) < 2e-15


def test_sin_cos_recurrence_drifts_without_reseeding_only_slowly():
    """Without the re-seeding the error grows (so the test above can tell), but stays at round-off size."""
    xs = 1.0 + 1e-3 * np.arange(200000)
    got = _recurrence(xs, 10**9)
    err = np.max(np.abs(got[:, 0] - np.sin(xs)))
    assert 1e-15 < err < 1e-11


@pytest.mark.parametrize("exponent", [0.5, 1.0, 2.0])
@pytest.mark.parametrize("fs_n, fc_n", [(25.0, 60.0), (100.0, 1.0), (1.0, 1000.0)])
def test_stribeck_term_beyond_the_cut_does_not_change_the_coulomb_force(exponent, fs_n, fc_n):
    cut = stribeck_cut_ratio(fs_n, fc_n, exponent)
    assert math.isfinite(cut)
    for ratio in (cut, cut * 1.01, cut * 3.0):
        assert fc_n + fs_n * math.exp(-(ratio**exponent)) == fc_n
    assert stribeck_cut_ratio(fs_n, 0.0, exponent) == math.inf
