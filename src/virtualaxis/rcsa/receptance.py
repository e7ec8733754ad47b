"""Receptance coupling of the ball-screw feed drive (seed 002, eqs. 1-24), compiled with numba.

Coordinates (seed 002 Figs. 4-6): the screw runs from point 1 (motor side, left bearing group, coupling
segment H) over point 2 (the nut, segment F, at distance ``l`` from point 1) to point 4 (right bearing
group, at ``L``). Axial and torsional substructures share these points. The worktable substructure has
the coordinates 6a (table axial), 5a (segment F axial) and 5t (segment F rotation).

Corrections of the printed equations (documented in docs/rcsa.md):

* eq. 1/2 print ``-cos(lambda l)`` on the diagonal; a free-free rod has ``-cot(lambda l)`` (eq. 10 has it
  right for torsion, and only ``cot`` gives the rigid-body limit ``-1/(m omega^2)``).
* eq. 6/8 print the joint receptance as ``[1/(k + i omega c)]^-1``; the receptance of a spring-damper is
  ``1/(k + i omega c)`` (what enters eq. 7/9).
* eq. 19/20 print ``-i_b k_n`` for the table/segment-F axial coupling; the nut spring stretches by
  ``x_b - x_s - i_b theta_s`` so the entry is ``-k_n`` (the printed matrix is dimensionally inconsistent).

The parameter vector ``p`` (float64[PARAM_COUNT]) holds, in this order, the constants in the
``P_*`` indices below; the eight joint values of eq. 25 sit at ``P_K_AL .. P_C_M``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from virtualaxis import jitcache  # noqa: F401  (numba cache failures are not fatal)

# index of each model constant in the parameter vector (SI units)
P_LENGTH_M = 0  # L, total screw length between the bearing groups [m]
P_AXIAL_RIGIDITY_N = 1  # E S [N]
P_AXIAL_WAVE_SLOWNESS_S_PER_M = 2  # sqrt(rho / E) [s/m]
P_TORSIONAL_RIGIDITY_NM2 = 3  # G J [N m^2]
P_TORSIONAL_WAVE_SLOWNESS_S_PER_M = 4  # sqrt(rho / G) [s/m]
P_LEAD_RATIO_M_PER_RAD = 5  # i_b = h / (2 pi) [m/rad]
P_NUT_SEGMENT_MASS_KG = 6  # m_s
P_NUT_SEGMENT_INERTIA_KG_M2 = 7  # J_s
P_COUPLING_SEGMENT_INERTIA_KG_M2 = 8  # J_sH (Table A "J_j")
P_TABLE_MASS_KG = 9  # m_b
P_ROTOR_INERTIA_KG_M2 = 10  # J_m
P_K_AL = 11  # left bearing group axial stiffness [N/m]
P_K_AR = 12  # right bearing group axial stiffness [N/m]
P_K_N = 13  # screw-nut axial stiffness [N/m]
P_K_M = 14  # coupling torsional stiffness [N m/rad]
P_C_AL = 15  # [N s/m]
P_C_AR = 16  # [N s/m]
P_C_N = 17  # [N s/m]
P_C_M = 18  # [N m s/rad]
P_ROTOR_HOLDING_STIFFNESS_NM_PER_RAD = 19  # rotor to ground (brake/servo during the test); 0 = free rotor
P_ROTOR_HOLDING_DAMPING_NM_S_PER_RAD = 20
PARAM_COUNT = 21
JOINT_SLICE = slice(P_K_AL, P_C_M + 1)


@njit(cache=True)
def _rod_receptances(lam: float, rigidity: float, length: float) -> tuple[float, float]:
    """Direct and cross receptance of a free-free uniform rod/shaft (eq. 1, 2, 10, 11).

    ``lam`` is the wavenumber [1/m], ``rigidity`` E S [N] or G J [N m^2]. Returns (h_11, h_12).
    """
    x = lam * length
    s = math.sin(x)
    if abs(s) < 1e-12:  # exactly on a free-free natural frequency: nudge off the pole
        x += 1e-9
        s = math.sin(x)
    scale = -1.0 / (rigidity * lam)
    return scale * math.cos(x) / s, scale / s


@njit(cache=True)
def _two_segment_receptances(
    lam: float, rigidity: float, length_a: float, length_b: float
) -> tuple[float, float, float, float, float, float]:
    """Segments A (1-2) and B (3-4) rigidly joined at 2 = 3 (eq. 4, 13).

    Returns the symmetric 3x3 receptance over (1, 2, 4) as (g11, g12, g14, g22, g24, g44)."""
    a11, a12 = _rod_receptances(lam, rigidity, length_a)
    b33, b34 = _rod_receptances(lam, rigidity, length_b)
    den = a11 + b33  # a22 = a11 for a uniform rod
    g11 = a11 - a12 * a12 / den
    g12 = a12 - a12 * a11 / den
    g14 = a12 * b34 / den
    g22 = a11 - a11 * a11 / den
    g24 = a11 * b34 / den
    g44 = b33 - b34 * b34 / den
    return g11, g12, g14, g22, g24, g44


@njit(cache=True)
def _ground_through(g: np.ndarray, i: int, joint_receptance: complex) -> None:
    """Couple coordinate ``i`` of the symmetric 3x3 receptance ``g`` (complex, in place) to a rigid body
    (h = 0, eq. 5) or to another substructure whose receptance there is ``joint_receptance``
    (eq. 7, 9, 17, 23, 24): G = H - H[:, i] H[i, :] / (H[i, i] + h_joint)."""
    den = g[i, i] + joint_receptance
    c0 = g[0, i]
    c1 = g[1, i]
    c2 = g[2, i]
    for r in range(3):
        cr = c0 if r == 0 else (c1 if r == 1 else c2)
        g[r, 0] = g[r, 0] - cr * c0 / den
        g[r, 1] = g[r, 1] - cr * c1 / den
        g[r, 2] = g[r, 2] - cr * c2 / den


@njit(cache=True)
def table_receptance(omega_rad_s: float, position_m: float, p: np.ndarray, work: np.ndarray) -> complex:
    """h_all-6a6a(omega) of eq. 24 at worktable position ``position_m`` (= l, from point 1) [m/N].

    ``work`` is a complex128 (3, 3) scratch array (kept by the caller so the loop does not allocate)."""
    w = omega_rad_s
    length_a = position_m
    length_b = p[P_LENGTH_M] - position_m
    iw = 1j * w
    # --- axial substructure (eqs. 1-9): points (1, 2, 4) ---
    lam_a = w * p[P_AXIAL_WAVE_SLOWNESS_S_PER_M]
    g11, g12, g14, g22, g24, g44 = _two_segment_receptances(lam_a, p[P_AXIAL_RIGIDITY_N], length_a, length_b)
    work[0, 0] = g11
    work[0, 1] = g12
    work[1, 0] = g12
    work[0, 2] = g14
    work[2, 0] = g14
    work[1, 1] = g22
    work[1, 2] = g24
    work[2, 1] = g24
    work[2, 2] = g44
    _ground_through(work, 0, 1.0 / (p[P_K_AL] + iw * p[P_C_AL]))  # eq. 7 (bed C rigid, eq. 5)
    _ground_through(work, 2, 1.0 / (p[P_K_AR] + iw * p[P_C_AR]))  # eq. 9
    h_axial_22 = work[1, 1]
    # --- torsional substructure (eqs. 10-17) ---
    lam_t = w * p[P_TORSIONAL_WAVE_SLOWNESS_S_PER_M]
    g11, g12, g14, g22, g24, g44 = _two_segment_receptances(
        lam_t, p[P_TORSIONAL_RIGIDITY_NM2], length_a, length_b
    )
    # rotor (J_m) -- coupling (k_m, c_m) -- segment H (J_sH): receptance at H (eqs. 14-16)
    zm = p[P_K_M] + iw * p[P_C_M]
    z_hold = p[P_ROTOR_HOLDING_STIFFNESS_NM_PER_RAD] + iw * p[P_ROTOR_HOLDING_DAMPING_NM_S_PER_RAD]
    d_rotor = zm + z_hold - w * w * p[P_ROTOR_INERTIA_KG_M2]
    d_h = zm - w * w * p[P_COUPLING_SEGMENT_INERTIA_KG_M2]
    h_h00 = d_rotor / (d_rotor * d_h - zm * zm)
    # eq. 17 keeps only what eq. 24 needs: h_AH-t22 = g22 - g12^2 / (g11 + h_H00)
    h_torsion_22 = g22 - g12 * g12 / (g11 + h_h00)
    # --- worktable substructure (eqs. 18-22): (6a, 5a, 5t) ---
    ib = p[P_LEAD_RATIO_M_PER_RAD]
    zn = p[P_K_N] + iw * p[P_C_N]
    # dynamic stiffness D = K + i w C - w^2 M, nut spring stretch x_b - x_s - i_b theta_s
    d00 = zn - w * w * p[P_TABLE_MASS_KG]
    d01 = -zn
    d02 = -ib * zn
    d11 = zn - w * w * p[P_NUT_SEGMENT_MASS_KG]
    d12 = ib * zn
    d22 = ib * ib * zn - w * w * p[P_NUT_SEGMENT_INERTIA_KG_M2]
    # symmetric 3x3 inverse by cofactors
    c00 = d11 * d22 - d12 * d12
    c01 = d02 * d12 - d01 * d22
    c02 = d01 * d12 - d02 * d11
    c11 = d00 * d22 - d02 * d02
    c12 = d01 * d02 - d00 * d12
    c22 = d00 * d11 - d01 * d01
    det = d00 * c00 + d01 * c01 + d02 * c02
    work[0, 0] = c00 / det
    work[0, 1] = c01 / det
    work[1, 0] = c01 / det
    work[0, 2] = c02 / det
    work[2, 0] = c02 / det
    work[1, 1] = c11 / det
    work[1, 2] = c12 / det
    work[2, 1] = c12 / det
    work[2, 2] = c22 / det
    # --- assembly: 5a rigid to axial point 2 (eq. 23), 5t rigid to torsional point 2 (eq. 24) ---
    _ground_through(work, 1, h_axial_22)
    _ground_through(work, 2, h_torsion_22)
    return work[0, 0]


@njit(cache=True)
def table_frf(freq_hz: np.ndarray, position_m: float, p: np.ndarray, out: np.ndarray) -> None:
    """Fill ``out`` (complex128, same length as ``freq_hz``) with h_all-6a6a [m/N]."""
    work = np.empty((3, 3), dtype=np.complex128)
    for k in range(freq_hz.shape[0]):
        out[k] = table_receptance(2.0 * math.pi * freq_hz[k], position_m, p, work)
