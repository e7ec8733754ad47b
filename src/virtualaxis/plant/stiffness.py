"""Stiffness formulas of ball-screw feed drives (seed 000 section 2.2, seed 004 section 3).

All functions take and return SI values (N/m, N m/rad, m).
"""

from __future__ import annotations

import math


def series(*stiffnesses: float) -> float:
    """Series combination 1/k = sum(1/k_i); a zero entry means 'rigid' and is skipped."""
    inv = sum(1.0 / k for k in stiffnesses if k > 0)
    return 1.0 / inv if inv > 0 else 0.0


def screw_area_m2(root_diameter_m: float) -> float:
    """Cross-section A_s of the screw core [m^2]."""
    return math.pi * root_diameter_m**2 / 4.0


def screw_polar_moment_m4(root_diameter_m: float) -> float:
    """Polar second moment I_p of the screw core [m^4]."""
    return math.pi * root_diameter_m**4 / 32.0


def screw_axial_stiffness_n_per_m(
    youngs_modulus_pa: float,
    root_diameter_m: float,
    length_m: float,
    nut_position_m: float,
    min_segment_m: float,
    mounting: str = "fixed_fixed",
) -> float:
    """Axial stiffness K_as of the screw seen by the nut at ``nut_position_m`` from the fixed bearing.

    fixed_fixed (seed 000): K_as = E A L / (x (L - x)); fixed_free: K_as = E A / x. ``x`` is clamped to
    ``[min_segment_m, L - min_segment_m]`` so the stiffness stays finite at the ends.
    """
    ea = youngs_modulus_pa * screw_area_m2(root_diameter_m)
    x = min(max(nut_position_m, min_segment_m), length_m - min_segment_m)
    if mounting == "fixed_fixed":
        return ea * length_m / (x * (length_m - x))
    return ea / x


def screw_torsional_stiffness_nm_per_rad(
    shear_modulus_pa: float, root_diameter_m: float, nut_position_m: float, min_segment_m: float
) -> float:
    """Torsional stiffness K_ts = G I_p / x of the screw between the driven end and the nut."""
    x = max(nut_position_m, min_segment_m)
    return shear_modulus_pa * screw_polar_moment_m4(root_diameter_m) / x


def nut_contact_stiffness_n_per_m(k_n0_n_per_m: float, preload_n: float, dynamic_load_rating_n: float) -> float:
    """Seed 000: K_an = 0.8 K_n0 (F_p / (0.1 C_n0))^(1/3)."""
    return 0.8 * k_n0_n_per_m * (preload_n / (0.1 * dynamic_load_rating_n)) ** (1.0 / 3.0)


def screw_inertia_kg_m2(density_kg_m3: float, root_diameter_m: float, length_m: float) -> float:
    """Rotary inertia of a solid cylindrical screw core, rho pi d^4 L / 32."""
    return density_kg_m3 * screw_polar_moment_m4(root_diameter_m) * length_m


def screw_mass_kg(density_kg_m3: float, root_diameter_m: float, length_m: float) -> float:
    return density_kg_m3 * screw_area_m2(root_diameter_m) * length_m


def equivalent_torsional_stiffness_nm_per_rad(
    k_tc: float, k_ts: float, k_as: float, k_an: float, k_ab: float, lead_m: float, efficiency: float = 1.0
) -> float:
    """Seed 000 eq. 5-7: 1/K_L = (2 pi / p)^2 eta / K_Z + 1/K_T, 1/K_T = 1/K_tc + 1/K_ts,
    1/K_Z = 1/K_as + 1/K_an + 1/K_ab (K_ab = K_ab1 + K_ab2)."""
    k_z = series(k_as, k_an, k_ab)
    k_t = series(k_tc, k_ts)
    inv = (2 * math.pi / lead_m) ** 2 * efficiency / k_z + 1.0 / k_t
    return 1.0 / inv
