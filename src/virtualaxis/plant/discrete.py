"""Exact (zero-order-hold) discretisation of the linear mechanics, per nut position and contact/stick mode.

The kernel steps ``z[k+1] = Ad z[k] + Bd u[k]`` with ``z = [q, q']``. Nonlinear elements switch between
precomputed linear modes at step boundaries: backlash (nut contact engaged or in the gap) and friction (table
sliding, or stuck: table rows frozen). Mode index = ``contact_gap + 2 * stuck`` with ``contact_gap`` 0 when the
contact spring is engaged and 1 in the gap. The stiffness depends on the nut position (K_as(x), torsion G I_p/x);
the tables are computed on a grid of nut positions and blended linearly by the kernel.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

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


def zoh_batch(a_list: list, b_list: list, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Zero-order-hold discretisation of many systems of one size in one batched matrix exponential, with
    BLAS limited to one thread (multithreaded BLAS on tiny matrices is slower by orders of magnitude)."""
    from scipy.linalg import expm
    from threadpoolctl import threadpool_limits

    s, m = a_list[0].shape[0], b_list[0].shape[1]
    aug = np.zeros((len(a_list), s + m, s + m))
    for i, (a, b) in enumerate(zip(a_list, b_list, strict=True)):
        aug[i, :s, :s] = a
        aug[i, :s, s:] = b
    with threadpool_limits(1):
        e = expm(aug * h)
    return e[:, :s, :s].copy(), e[:, :s, s:].copy()


def zoh(a: np.ndarray, b: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Zero-order-hold discretisation via the augmented matrix exponential."""
    from scipy.linalg import expm

    s, m = a.shape[0], b.shape[1]
    aug = np.zeros((s + m, s + m))
    aug[:s, :s] = a
    aug[:s, s:] = b
    e = expm(aug * h)
    return e[:s, :s].copy(), e[:s, s:].copy()


CACHE_VERSION = 1  # bump when the mechanics equations change


def cache_dir() -> Path:
    """Where discretised tables are cached (``VIRTUALAXIS_CACHE_DIR`` or ``~/.cache/virtualaxis``)."""
    base = os.environ.get("VIRTUALAXIS_CACHE_DIR") or os.path.join(os.path.expanduser("~"), ".cache", "virtualaxis")
    return Path(base) / "discrete"


def _cache_key(cfg: AxisConfig, step_s: float, grid_points: int, support_scale: float) -> str:
    relevant = {k: dataclasses.asdict(getattr(cfg, k)) for k in ("axis", "mechanics", "actuator", "effects")}
    relevant["effects"] = {k: v for k, v in relevant["effects"].items() if k.startswith("resonance")}
    blob = json.dumps([CACHE_VERSION, relevant, step_s, grid_points, support_scale], sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:24]


def discretise(
    cfg: AxisConfig, step_s: float, grid_points: int | None = None, support_scale: float = 1.0, *, cache: bool = True
) -> DiscreteMechanics:
    """Mode tables for the kernel at mechanical step ``step_s``, cached on disk by the mechanical parameters
    (a second start of the same axis skips the matrix exponentials)."""
    npts = grid_points or cfg.simulation.position_grid_points
    path = cache_dir() / f"{_cache_key(cfg, step_s, npts, support_scale)}.npz"
    if cache and path.exists():
        try:
            with np.load(path, allow_pickle=False) as z:
                meta = json.loads(str(z["meta"]))
                arrays = {k: z[k] for k in z.files if k != "meta"}
            return DiscreteMechanics(**arrays, **meta)
        except (OSError, ValueError, KeyError, TypeError):
            pass  # a damaged cache entry is rebuilt
    dm = _discretise(cfg, step_s, npts, support_scale)
    if cache:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            arrays = {f.name: getattr(dm, f.name) for f in dataclasses.fields(dm)
                      if isinstance(getattr(dm, f.name), np.ndarray)}
            meta = {f.name: getattr(dm, f.name) for f in dataclasses.fields(dm) if f.name not in arrays}
            tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
            np.savez(tmp, meta=json.dumps(meta), **arrays)
            os.replace(tmp, path)
        except OSError:
            pass  # caching is an optimisation only
    return dm


def _discretise(cfg: AxisConfig, step_s: float, npts: int, support_scale: float) -> DiscreteMechanics:
    lo, hi = nut_position_range_m(cfg)
    grid = np.array([lo]) if hi <= lo else np.linspace(lo, hi, max(npts, 2))
    b_struct = structural_damping_coefficient(cfg)
    mech0 = build_mechanics(cfg, grid[0], support_scale=support_scale)
    n = mech0.n
    s = 2 * n
    ad = np.zeros((len(grid), N_MODES, s, s))
    bd = np.zeros((len(grid), N_MODES, s, N_INPUTS))
    krow = np.zeros((len(grid), 2, n))
    crow = np.zeros((len(grid), 2, n))
    conts = []  # continuous (A, B) per grid point and mode, exponentiated in one batch below
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
                conts.append((gi, cg + 2 * stuck, *_continuous(mass, k, c, g, t, bool(stuck))))
    ads, bds = zoh_batch([a for *_, a, _b in conts], [b for *_, b in conts], step_s)
    for (gi, mode, _a, _b), a_d, b_d in zip(conts, ads, bds, strict=True):
        ad[gi, mode], bd[gi, mode] = a_d, b_d
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
        contact_stiffness=float(kc),
        contact_damping=float(b_struct * kc),
        motor_angle_vector=mech0.motor_angle_vector.copy(),
        screw_body=-1 if mech0.screw_body is None else int(mech0.screw_body),
        table_body=int(mech0.table_body),
        n=int(n),
        step_s=float(step_s),
        structural_b=float(b_struct),
        body_names=[b.name for b in mech0.bodies],
    )
