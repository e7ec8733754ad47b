"""Lumped mechanics as bodies and springs (Modelica-style components, SI parameters).

A :class:`Mechanics` is assembled from an :class:`~virtualaxis.config.AxisConfig`:

- ``ball_screw`` (seed 004, six bodies): motor rotor ``theta_m`` [rad], screw end ``theta_e`` [rad], screw
  ``theta_s`` [rad], screw axial ``x_s`` [m], nut ``x_n`` [m], table ``x_t`` [m]. Springs: motor shaft + coupling
  (torsion), screw end + screw torsion G I_p / x (nut-position dependent), axial support + bearings + screw
  K_as(x) in series (nut-position dependent), nut contact K_an between ``x_s + r theta_s`` and ``x_n`` (the
  backlash element), nut flange. A zero flange stiffness merges nut and table.
- ``two_mass``: rotor (with screw and coupling inertia) and table through one equivalent spring (the contact
  element, so backlash can sit in it).
- ``rigid``: one body, the table (rotor inertia reflected through the lead for a pmsm).

An optional extra mode (``effects.resonance_*``) hangs a modal mass on the table by a spring.

Equations: ``M q'' + C q' + K(x_nut) q = G u`` with inputs ``u = [actuator, friction, external, contact]``:
actuator torque on the rotor [N m] (or force on the table [N]), friction force on the table [N], external force
on the table [N], and the contact offset force (see :mod:`virtualaxis.plant.backlash`). Damping is structural,
``C = b K`` with ``b = 2 zeta / omega_1`` from the modal damping ratio of the first non-zero mode at mid-stroke
(seed 004 eqs. 19-21), plus explicit viscous dampers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from virtualaxis.config import AxisConfig
from virtualaxis.plant import stiffness as stf

U_ACTUATOR, U_FRICTION, U_EXTERNAL, U_CONTACT = 0, 1, 2, 3
N_INPUTS = 4


@dataclass
class Body:
    name: str
    kind: str  # "rot" [rad] or "lin" [m]
    inertia: float  # kg m^2 or kg


@dataclass
class Spring:
    name: str
    incidence: dict[int, float]  # body index -> coefficient of the relative displacement
    stiffness: float  # N/m or N m/rad (in the units of the relative displacement)
    damping: float = 0.0  # explicit damper in parallel [N s/m or N m s/rad]


@dataclass
class Mechanics:
    """Assembled mechanics at one nut position. ``contact`` is the backlash element (or None)."""

    bodies: list[Body]
    springs: list[Spring]
    contact: Spring | None
    motor_body: int | None  # rotor body (None: no rotary motor body)
    table_body: int
    screw_body: int | None  # body whose angle drives the nut (lead error, thermal)
    lead_m: float
    actuator_vector: np.ndarray  # generalised force per unit actuator input
    motor_angle_vector: np.ndarray  # motor angle = this . q
    ground_dampers: dict[int, float] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return len(self.bodies)

    def mass_matrix(self) -> np.ndarray:
        return np.diag([b.inertia for b in self.bodies])

    def incidence(self, spring: Spring) -> np.ndarray:
        a = np.zeros(self.n)
        for i, c in spring.incidence.items():
            a[i] += c
        return a

    def stiffness_matrix(self, with_contact: bool = True) -> np.ndarray:
        k = np.zeros((self.n, self.n))
        for s in self.springs:
            a = self.incidence(s)
            k += s.stiffness * np.outer(a, a)
        if with_contact and self.contact is not None:
            a = self.incidence(self.contact)
            k += self.contact.stiffness * np.outer(a, a)
        return k

    def explicit_damping_matrix(self, with_contact: bool = True) -> np.ndarray:
        c = np.zeros((self.n, self.n))
        for s in self.springs + ([self.contact] if (with_contact and self.contact) else []):
            if s.damping:
                a = self.incidence(s)
                c += s.damping * np.outer(a, a)
        for i, d in self.ground_dampers.items():
            c[i, i] += d
        return c

    def input_matrix(self) -> np.ndarray:
        g = np.zeros((self.n, N_INPUTS))
        g[:, U_ACTUATOR] = self.actuator_vector
        g[self.table_body, U_FRICTION] = 1.0
        g[self.table_body, U_EXTERNAL] = 1.0
        if self.contact is not None:
            g[:, U_CONTACT] = -self.incidence(self.contact)
        return g


def screw_geometry(cfg: AxisConfig) -> tuple[float, float]:
    """(screw rotary inertia [kg m^2], screw mass [kg]) from the configured core diameter and length."""
    m = cfg.mechanics
    if m.screw_root_diameter_m <= 0 or m.screw_length_m <= 0:
        return 0.0, 0.0
    return (
        stf.screw_inertia_kg_m2(m.screw_density_kg_m3, m.screw_root_diameter_m, m.screw_length_m),
        stf.screw_mass_kg(m.screw_density_kg_m3, m.screw_root_diameter_m, m.screw_length_m),
    )


def nut_position_m(cfg: AxisConfig, table_position_m: float) -> float:
    """Distance of the nut from the fixed (driven-end) bearing for a table position."""
    return cfg.axis.nut_offset_m + table_position_m


def nut_position_range_m(cfg: AxisConfig) -> tuple[float, float]:
    """Nut positions at which the mechanics are discretised (the clamped screw length)."""
    m = cfg.mechanics
    if m.model != "ball_screw":
        return (cfg.axis.nut_offset_m, cfg.axis.nut_offset_m)
    return (m.min_segment_m, m.screw_length_m - m.min_segment_m)


def reflected_inertia_kg_m2(cfg: AxisConfig) -> float:
    """Total inertia seen at the motor shaft (rigid), used for gains and feed-forward."""
    m = cfg.mechanics
    j_screw, _ = screw_geometry(cfg)
    r = m.lead_m / (2 * math.pi)
    moving = m.table_mass_kg + m.nut_mass_kg + cfg.effects.resonance_mass_kg
    return m.motor_inertia_kg_m2 + m.coupling_inertia_kg_m2 + m.screw_end_inertia_kg_m2 + j_screw + moving * r * r


def feedforward_inertia(cfg: AxisConfig) -> float:
    """What the torque feed-forward multiplies the commanded acceleration by, in drive units: the reflected
    inertia at the motor shaft [kg m^2], or the moving mass [kg] for a force actuator."""
    if cfg.actuator.kind == "force":
        return cfg.mechanics.table_mass_kg + cfg.mechanics.nut_mass_kg
    return reflected_inertia_kg_m2(cfg)


def build_mechanics(cfg: AxisConfig, nut_pos_m: float, *, support_scale: float = 1.0) -> Mechanics:
    """Assemble bodies and springs at one nut position (``support_scale`` scales the support stiffness)."""
    m = cfg.mechanics
    r = m.lead_m / (2 * math.pi)
    bodies: list[Body] = []
    springs: list[Spring] = []
    contact = None
    motor_body = screw_body = None
    ground: dict[int, float] = {}
    is_pmsm = cfg.actuator.kind == "pmsm"

    def add(name: str, kind: str, inertia: float) -> int:
        bodies.append(Body(name, kind, inertia))
        return len(bodies) - 1

    if m.model == "ball_screw":
        j_screw, m_screw = screw_geometry(cfg)
        motor_body = add("motor", "rot", m.motor_inertia_kg_m2 + m.coupling_inertia_kg_m2 / 2)
        end = add("screw_end", "rot", m.screw_end_inertia_kg_m2 + m.coupling_inertia_kg_m2 / 2)
        screw_body = add("screw", "rot", j_screw)
        screw_ax = add("screw_axial", "lin", m_screw)
        merged = m.flange_stiffness_n_per_m <= 0
        nut = None if merged else add("nut", "lin", m.nut_mass_kg)
        table = add("table", "lin", m.table_mass_kg + (m.nut_mass_kg if merged else 0.0))
        nut_or_table = table if nut is None else nut
        springs.append(
            Spring(
                "coupling",
                {motor_body: 1.0, end: -1.0},
                stf.series(m.coupling_stiffness_nm_per_rad, m.motor_shaft_stiffness_nm_per_rad),
            )
        )
        k_ts = stf.screw_torsional_stiffness_nm_per_rad(
            m.shear_modulus_pa, m.screw_root_diameter_m, nut_pos_m, m.min_segment_m
        )
        k_torsion = stf.series(m.screw_end_stiffness_nm_per_rad, k_ts)
        springs.append(Spring("screw_torsion", {end: 1.0, screw_body: -1.0}, k_torsion))
        k_as = stf.screw_axial_stiffness_n_per_m(
            m.youngs_modulus_pa, m.screw_root_diameter_m, m.screw_length_m, nut_pos_m, m.min_segment_m, m.screw_mounting
        )
        k_axial = stf.series(m.support_axial_stiffness_n_per_m * support_scale, m.bearing_axial_stiffness_n_per_m, k_as)
        springs.append(Spring("axial_support", {screw_ax: 1.0}, k_axial))
        contact = Spring(
            "nut_contact", {screw_ax: 1.0, screw_body: r, nut_or_table: -1.0}, m.nut_contact_stiffness_n_per_m
        )
        if nut is not None:
            springs.append(Spring("flange", {nut: 1.0, table: -1.0}, m.flange_stiffness_n_per_m))
        act = np.zeros(len(bodies))
        if is_pmsm:
            act[motor_body] = 1.0
        else:
            act[table] = 1.0
        ground[motor_body] = m.motor_viscous_nm_s_per_rad
    elif m.model == "two_mass":
        j_screw, _ = screw_geometry(cfg)
        motor_body = add(
            "motor", "rot", m.motor_inertia_kg_m2 + m.coupling_inertia_kg_m2 + m.screw_end_inertia_kg_m2 + j_screw
        )
        screw_body = motor_body
        table = add("table", "lin", m.table_mass_kg + m.nut_mass_kg)
        k_lin = m.equivalent_torsional_stiffness_nm_per_rad / r**2
        contact = Spring("drive_spring", {motor_body: r, table: -1.0}, k_lin)
        act = np.zeros(len(bodies))
        act[motor_body if is_pmsm else table] = 1.0
        ground[motor_body] = m.motor_viscous_nm_s_per_rad
    else:  # rigid
        j_rot = m.motor_inertia_kg_m2 + m.coupling_inertia_kg_m2 + m.screw_end_inertia_kg_m2 + screw_geometry(cfg)[0]
        mass = m.table_mass_kg + m.nut_mass_kg + (j_rot / r**2 if m.lead_m > 0 else 0.0)
        table = add("table", "lin", mass)
        act = np.zeros(1)
        act[table] = (1.0 / r) if is_pmsm else 1.0
        if m.lead_m > 0:
            ground_motor = m.motor_viscous_nm_s_per_rad / r**2
            ground[table] = ground.get(table, 0.0) + ground_motor

    ground[table] = ground.get(table, 0.0) + m.table_viscous_n_s_per_m
    e = cfg.effects
    if e.resonance_frequency_hz > 0:
        res = add("resonator", "lin", e.resonance_mass_kg)
        k_r = e.resonance_mass_kg * (2 * math.pi * e.resonance_frequency_hz) ** 2
        c_r = 2 * e.resonance_damping_ratio * math.sqrt(k_r * e.resonance_mass_kg)
        springs.append(Spring("resonance", {table: 1.0, res: -1.0}, k_r, damping=c_r))
    n = len(bodies)
    act_full = np.zeros(n)
    act_full[: len(act)] = act
    motor_angle = np.zeros(n)
    if motor_body is not None:
        motor_angle[motor_body] = 1.0
    elif m.lead_m > 0:
        motor_angle[table] = 1.0 / r
    return Mechanics(
        bodies=bodies,
        springs=springs,
        contact=contact,
        motor_body=motor_body,
        table_body=table,
        screw_body=screw_body,
        lead_m=m.lead_m,
        actuator_vector=act_full,
        motor_angle_vector=motor_angle,
        ground_dampers=ground,
    )


def natural_frequencies_rad_s(mass: np.ndarray, stiff: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undamped eigenproblem K phi = w^2 M phi; returns (omega ascending [rad/s], mode shapes as columns)."""
    from scipy.linalg import eigh

    w2, phi = eigh(stiff, mass)
    w2 = np.clip(w2, 0.0, None)
    return np.sqrt(w2), phi


def structural_damping_coefficient(cfg: AxisConfig) -> float:
    """b in C = b K from the modal damping ratio of the first non-zero mode at mid-stroke (seed 004 eq. 21)."""
    zeta = cfg.mechanics.modal_damping_ratio
    if zeta <= 0:
        return 0.0
    mech = build_mechanics(cfg, nut_position_m(cfg, 0.0))
    w, _ = natural_frequencies_rad_s(mech.mass_matrix(), mech.stiffness_matrix(True))
    nz = w[w > 1e-3 * max(w.max(), 1.0)]
    nz = nz[nz > 1e-6]
    if nz.size == 0:
        return 0.0
    return 2.0 * zeta / nz[0]


def damping_matrix(mech: Mechanics, b: float, with_contact: bool = True) -> np.ndarray:
    """Structural damping b K (excluding the resonator, whose damping is explicit) plus explicit dampers."""
    k = np.zeros((mech.n, mech.n))
    for s in mech.springs:
        if s.name == "resonance":
            continue
        a = mech.incidence(s)
        k += s.stiffness * np.outer(a, a)
    if with_contact and mech.contact is not None:
        a = mech.incidence(mech.contact)
        k += mech.contact.stiffness * np.outer(a, a)
    return b * k + mech.explicit_damping_matrix(with_contact)
