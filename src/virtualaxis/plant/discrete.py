"""Exact (zero-order-hold) discretisation of the linear mechanics, per nut position and contact/stick mode.

The kernel steps ``z[k+1] = Ad z[k] + Bd u[k]`` with ``z = [q, q']``. Nonlinear elements switch between
precomputed linear modes at step boundaries: backlash (nut contact engaged or in the gap) and friction (table
sliding, or stuck: table rows frozen). Mode index = ``contact_gap + 2 * stuck`` with ``contact_gap`` 0 when the
contact spring is engaged and 1 in the gap. The stiffness depends on the nut position (K_as(x), torsion G I_p/x);
the tables are computed on a grid of nut positions and blended linearly by the kernel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from virtualaxis.config import AxisConfig
from virtualaxis.plant.mechanics import (
    N_INPUTS,
    build_mechanics,
    damping_matrix,
    nut_position_range_m,
    structural_damping_coefficient,
)

MODE_CONTACT, MODE_GAP = 0, 1
N_MODES = 4


@dataclass
class DiscreteMechanics:
    grid_m: np.ndarray  # (G,) nut positions from the fixed bearing [m]
    ad: np.ndarray  # (G, 4, S, S)
    bd: np.ndarray  # (G, 4, S, N_INPUTS)
    table_k_row: np.ndarray  # (G, 2, n): row of K for the table body (contact, gap)
    table_c_row: np.ndarray  # (G, 2, n)
    table_g_row: np.ndarray  # (N_INPUTS,)
    contact_vector: np.ndarray  # (n,) incidence of the contact element (zeros if none)
    contact_stiffness: float
    contact_damping: float
    motor_angle_vector: np.ndarray  # (n,)
    screw_body: int  # -1 if none
    table_body: int
    n: int
    step_s: float
    structural_b: float
    body_names: list


def _continuous(mass, stiff, damp, g, table, stuck):
    n = mass.shape[0]
    minv = np.linalg.inv(mass)
    a = np.zeros((2 * n, 2 * n))
    a[:n, n:] = np.eye(n)
    a[n:, :n] = -minv @ stiff
    a[n:, n:] = -minv @ damp
    b = np.zeros((2 * n, g.shape[1]))
    b[n:, :] = minv @ g
    if stuck:
        for row in (table, n + table):
            a[row, :] = 0.0
            b[row, :] = 0.0
    return a, b


def zoh(a: np.ndarray, b: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Zero-order-hold discretisation via the augmented matrix exponential."""
    s, m = a.shape[0], b.shape[1]
    aug = np.zeros((s + m, s + m))
    aug[:s, :s] = a
    aug[:s, s:] = b
    e = expm(aug * h)
    return e[:s, :s].copy(), e[:s, s:].copy()


def discretise(
    cfg: AxisConfig, step_s: float, grid_points: int | None = None, support_scale: float = 1.0
) -> DiscreteMechanics:
    """Build the mode tables for the kernel at mechanical step ``step_s``."""
    lo, hi = nut_position_range_m(cfg)
    npts = grid_points or cfg.simulation.position_grid_points
    grid = np.array([lo]) if hi <= lo else np.linspace(lo, hi, max(npts, 2))
    b_struct = structural_damping_coefficient(cfg)
    mech0 = build_mechanics(cfg, grid[0], support_scale=support_scale)
    n = mech0.n
    s = 2 * n
    ad = np.zeros((len(grid), N_MODES, s, s))
    bd = np.zeros((len(grid), N_MODES, s, N_INPUTS))
    krow = np.zeros((len(grid), 2, n))
    crow = np.zeros((len(grid), 2, n))
    for gi, x in enumerate(grid):
        mech = build_mechanics(cfg, x, support_scale=support_scale)
        mass = mech.mass_matrix()
        g = mech.input_matrix()
        t = mech.table_body
        for cg, with_contact in ((MODE_CONTACT, True), (MODE_GAP, False)):
            k = mech.stiffness_matrix(with_contact)
            c = damping_matrix(mech, b_struct, with_contact)
            krow[gi, cg] = k[t]
            crow[gi, cg] = c[t]
            for stuck in (0, 1):
                a, b = _continuous(mass, k, c, g, t, bool(stuck))
                ad[gi, cg + 2 * stuck], bd[gi, cg + 2 * stuck] = zoh(a, b, step_s)
    contact_vec = mech0.incidence(mech0.contact) if mech0.contact is not None else np.zeros(n)
    kc = mech0.contact.stiffness if mech0.contact is not None else 0.0
    return DiscreteMechanics(
        grid_m=grid,
        ad=ad,
        bd=bd,
        table_k_row=krow,
        table_c_row=crow,
        table_g_row=mech0.input_matrix()[mech0.table_body].copy(),
        contact_vector=contact_vec,
        contact_stiffness=kc,
        contact_damping=b_struct * kc,
        motor_angle_vector=mech0.motor_angle_vector.copy(),
        screw_body=-1 if mech0.screw_body is None else mech0.screw_body,
        table_body=mech0.table_body,
        n=n,
        step_s=step_s,
        structural_b=b_struct,
        body_names=[b.name for b in mech0.bodies],
    )
