"""An independent finite-element model of the same feed drive, for cross-checking the RCSA model.

Two-node rod elements (consistent mass) for the screw's axial and torsional motion, ``n`` elements
per screw segment so that the nut sits on a node; the joints, rigid segments F and H, rotor and table
are lumped exactly as in seed 002 Figs. 2-6 (nut spring stretched by x_b - x_s - i_b theta_s).
Undamped natural frequencies come from the generalised eigenproblem K v = w^2 M v; the damped table
FRF h_6a6a from solving (K + i w C - w^2 M) x = e_table per frequency.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from virtualaxis.rcsa.params import JointParams, RcsaModel


@dataclass(frozen=True)
class FeMatrices:
    """M, K, C (n x n) and the index of the table DOF."""

    mass: np.ndarray
    stiffness: np.ndarray
    damping: np.ndarray
    table_dof: int


def _segment_nodes(position_m: float, length_m: float, elements_per_metre: float) -> np.ndarray:
    n_a = max(4, math.ceil(position_m * elements_per_metre))
    n_b = max(4, math.ceil((length_m - position_m) * elements_per_metre))
    return np.concatenate(
        [np.linspace(0.0, position_m, n_a + 1), np.linspace(position_m, length_m, n_b + 1)[1:]]
    )


def fe_matrices(
    model: RcsaModel, position_m: float, joints: JointParams | None = None, elements_per_metre: float = 80.0
) -> FeMatrices:
    """Assemble the FE matrices at worktable position ``position_m`` (distance of the nut from point 1)."""
    model.check_position(position_m)
    s, q = model.screw, model.parts
    j = joints or model.joints
    x = _segment_nodes(position_m, s.length_m, elements_per_metre)
    n_nodes = x.size
    nut = int(np.argmin(np.abs(x - position_m)))
    # DOFs in band order: rotor, (u_0, th_0), ..., (u_nut, th_nut), table, (u_nut+1, th_nut+1), ...
    rotor = 0
    ax = np.empty(n_nodes, dtype=np.int64)
    tor = np.empty(n_nodes, dtype=np.int64)
    k = 1
    table = -1
    for i in range(n_nodes):
        ax[i], tor[i] = k, k + 1
        k += 2
        if i == nut:
            table = k
            k += 1
    n = k
    mass = np.zeros((n, n))
    stiff = np.zeros((n, n))
    damp = np.zeros((n, n))
    ea = s.youngs_modulus_pa * s.area_m2
    gj = s.shear_modulus_pa * s.polar_moment_m4
    rho_a = s.density_kg_m3 * s.area_m2
    rho_j = s.density_kg_m3 * s.polar_moment_m4
    k_unit = np.array([[1.0, -1.0], [-1.0, 1.0]])
    m_unit = np.array([[2.0, 1.0], [1.0, 2.0]]) / 6.0
    for e in range(n_nodes - 1):
        le = x[e + 1] - x[e]
        for dofs, rig, dens in ((ax[e : e + 2], ea, rho_a), (tor[e : e + 2], gj, rho_j)):
            stiff[np.ix_(dofs, dofs)] += rig / le * k_unit
            mass[np.ix_(dofs, dofs)] += dens * le * m_unit
    # bearing groups (eq. 6, 8) at the two ends
    stiff[ax[0], ax[0]] += j.k_al
    damp[ax[0], ax[0]] += j.c_al
    stiff[ax[-1], ax[-1]] += j.k_ar
    damp[ax[-1], ax[-1]] += j.c_ar
    # segment H, coupling, rotor (eqs. 14-16) and the rotor hold
    mass[tor[0], tor[0]] += q.coupling_segment_inertia_kg_m2
    mass[rotor, rotor] += q.rotor_inertia_kg_m2
    pair = [rotor, tor[0]]
    stiff[np.ix_(pair, pair)] += j.k_m * k_unit
    damp[np.ix_(pair, pair)] += j.c_m * k_unit
    stiff[rotor, rotor] += q.rotor_holding_stiffness_nm_per_rad
    damp[rotor, rotor] += q.rotor_holding_damping_nm_s_per_rad
    # segment F and worktable (eqs. 18-21): stretch = x_b - u_nut - i_b th_nut
    mass[ax[nut], ax[nut]] += q.nut_segment_mass_kg
    mass[tor[nut], tor[nut]] += q.nut_segment_inertia_kg_m2
    mass[table, table] += q.table_mass_kg
    ib = s.lead_ratio_m_per_rad
    b = np.zeros(n)
    b[table], b[ax[nut]], b[tor[nut]] = 1.0, -1.0, -ib
    stiff += j.k_n * np.outer(b, b)
    damp += j.c_n * np.outer(b, b)
    return FeMatrices(mass, stiff, damp, table)


def fe_natural_frequencies_hz(
    model: RcsaModel, position_m: float, joints: JointParams | None = None, elements_per_metre: float = 80.0
) -> np.ndarray:
    """Undamped natural frequencies [Hz], ascending (rigid-body modes come out near 0)."""
    fm = fe_matrices(model, position_m, joints, elements_per_metre)
    w2 = scipy.linalg.eigh(fm.stiffness, fm.mass, eigvals_only=True)
    return np.sqrt(np.clip(w2, 0.0, None)) / (2.0 * math.pi)


def fe_table_frf(
    model: RcsaModel,
    position_m: float,
    freq_hz: np.ndarray,
    joints: JointParams | None = None,
    elements_per_metre: float = 80.0,
) -> np.ndarray:
    """Damped table FRF h_6a6a [m/N] of the FE model on ``freq_hz``."""
    fm = fe_matrices(model, position_m, joints, elements_per_metre)
    n = fm.mass.shape[0]
    rhs = np.zeros(n, dtype=np.complex128)
    rhs[fm.table_dof] = 1.0
    rows, cols = np.nonzero((fm.stiffness != 0) | (fm.mass != 0) | (fm.damping != 0))
    lower = int(np.max(rows - cols))
    upper = int(np.max(cols - rows))
    out = np.empty(freq_hz.size, dtype=np.complex128)
    band = np.zeros((lower + upper + 1, n), dtype=np.complex128)
    for k, f in enumerate(freq_hz):
        w = 2.0 * math.pi * f
        dyn = fm.stiffness + 1j * w * fm.damping - w * w * fm.mass
        for d in range(-lower, upper + 1):  # diagonal d (column - row) into banded storage
            diag = np.diagonal(dyn, offset=d)
            if d >= 0:
                band[upper - d, d:] = diag
            else:
                band[upper - d, : n + d] = diag
        out[k] = scipy.linalg.solve_banded((lower, upper), band, rhs)[fm.table_dof]
    return out
