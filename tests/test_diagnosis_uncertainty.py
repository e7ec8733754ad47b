"""Parameter uncertainty of a fit whose model is chaotic (fit.chaos_corrected_covariance).

A synthetic least-squares problem with a known answer: residual = signal columns x parameter + chaos. Each
simulation at new parameters draws new chaos, as the quantised stick-slip loop does."""

import math

import numpy as np

from virtualaxis.diagnosis.fit import chaos_corrected_covariance


def _secant(signal: np.ndarray, h: np.ndarray, chaos_rms: float, rng) -> tuple[np.ndarray, float]:
    """Secant columns of r(u) = signal @ u + chaos(u) at u = 0 and one chaos difference (same u, new draw)."""
    m, k = signal.shape
    c0 = rng.normal(0.0, chaos_rms, m)
    cols = [(signal[:, j] * h[j] + rng.normal(0.0, chaos_rms, m) - c0) / h[j] for j in range(k)]
    diff = rng.normal(0.0, chaos_rms, m) - c0
    return np.column_stack(cols), float(diff @ diff)


def test_without_chaos_it_is_the_classical_covariance():
    rng = np.random.default_rng(0)
    jac = rng.normal(size=(500, 3))
    cov = chaos_corrected_covariance(jac, np.full(3, 0.15), 0.0, 2.0)
    np.testing.assert_allclose(cov, 2.0 * np.linalg.inv(jac.T @ jac), rtol=1e-10)


def test_chaos_is_taken_out_of_the_information():
    # one parameter well above the chaos: its variance must match the chaos-free one, not the smaller
    # value the chaos-inflated column would give
    rng = np.random.default_rng(1)
    m, h = 20000, np.array([0.15])
    signal = np.full((m, 1), 1.0)  # response per unit parameter: energy m per unit^2
    jac, chaos_sq = _secant(signal, h, chaos_rms=0.2, rng=rng)
    plain = 1.0 / float(jac[:, 0] @ jac[:, 0])
    exact = 1.0 / float(signal[:, 0] @ signal[:, 0])
    cov = chaos_corrected_covariance(jac, h, chaos_sq, 1.0)
    assert plain < 0.3 * exact  # the raw secant column is mostly chaos: far too confident
    assert abs(cov[0, 0] / exact - 1.0) < 0.1


def test_a_parameter_buried_in_chaos_is_not_determined():
    rng = np.random.default_rng(2)
    m, h = 20000, np.array([0.15, 0.15])
    signal = np.column_stack([np.full(m, 1.0), np.full(m, 0.01)])  # the second barely moves the residual
    jac, chaos_sq = _secant(signal, h, chaos_rms=0.2, rng=rng)
    cov = chaos_corrected_covariance(jac, h, chaos_sq, 1.0)
    assert math.isfinite(cov[0, 0])
    assert cov[1, 1] == math.inf
    # the classical formula claims it is known to a few percent of one secant step
    assert math.sqrt(np.linalg.inv(jac.T @ jac)[1, 1]) < 0.1 * h[1]


def test_amplitude_and_phase_errors_follow_from_the_components():
    from virtualaxis.diagnosis.effects import derived_stderr

    rng = np.random.default_rng(3)
    c, s, sc, ss = 0.3, 0.4, 0.01, 0.02
    cc, sn = c + sc * rng.normal(size=200000), s + ss * rng.normal(size=200000)
    out = derived_stderr("torque_ripple", {"cogging_cos_nm": c, "cogging_sin_nm": s},
                         {"cogging_cos_nm": sc, "cogging_sin_nm": ss})
    assert abs(out["cogging_amplitude_nm"] / np.std(np.hypot(cc, sn)) - 1) < 0.03
    assert abs(out["cogging_phase_rad"] / np.std(np.arctan2(sn, cc)) - 1) < 0.03
    loose = derived_stderr("torque_ripple", {"cogging_cos_nm": c, "cogging_sin_nm": s},
                           {"cogging_cos_nm": math.inf, "cogging_sin_nm": ss})
    assert loose["cogging_amplitude_nm"] == math.inf and loose["cogging_phase_rad"] == math.inf


def test_one_short_trace_can_determine_what_the_pooled_chaos_buries():
    # a long trace of pure chatter and a short one where the parameter rings well above its own chatter (a
    # rapid move exciting a mode): pooled, the long trace's chaos buries it; trace by trace it is determined,
    # with the variance its signal gives. A parameter no trace determines stays undetermined.
    rng = np.random.default_rng(4)
    n_long, n_short, h = 40000, 2000, np.array([0.15, 0.15])
    signal = np.zeros((n_long + n_short, 2))
    signal[n_long:, 0] = 3.0 * np.sin(np.arange(n_short) * 0.3)  # step energy ~200 vs chaos ~160 (pooled ~3400)
    signal[n_long:, 1] = 0.001
    jac, _ = _secant(signal, h, chaos_rms=0.2, rng=rng)
    rows = [slice(0, n_long), slice(n_long, n_long + n_short)]
    # one chaos difference per trace (the same draw process as the columns)
    diff = rng.normal(0.0, 0.2, n_long + n_short) - rng.normal(0.0, 0.2, n_long + n_short)
    per_trace = [float(diff[r] @ diff[r]) for r in rows]
    pooled = chaos_corrected_covariance(jac, h, sum(per_trace), 1.0)
    assert pooled[0, 0] == math.inf
    cov = chaos_corrected_covariance(jac, h, per_trace, 1.0, segments=rows)
    exact = 1.0 / float(signal[:, 0] @ signal[:, 0])
    assert abs(cov[0, 0] / exact - 1.0) < 0.25
    assert cov[1, 1] == math.inf
