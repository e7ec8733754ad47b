"""Modal analysis of the lumped mechanics (seed 004 section 4) as a function of nut position.

Natural frequencies and mode shapes solve the undamped problem ``K phi = w^2 M phi`` with the nut contact
engaged; modal damping ratios are the diagonal of the damping matrix in modal coordinates,
``zeta_i = phi_i^T C phi_i / (2 w_i phi_i^T M phi_i)`` (exact for the structural C = b K, the classical
approximation for the explicit dampers).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from virtualaxis.config import AxisConfig
from virtualaxis.plant.mechanics import (
    build_mechanics,
    damping_matrix,
    natural_frequencies_rad_s,
    structural_damping_coefficient,
)

RIGID_BODY_HZ = 1e-2  # modes below this are rigid-body modes


@dataclass
class ModalResult:
    nut_position_m: float
    natural_frequencies_hz: list[float]
    damping_ratios: list[float]
    mode_shapes: list[list[float]]  # one list per mode, per body, max-normalised
    body_names: list[str]
    spring_deformations: list[dict[str, float]]  # strain-energy share of each spring per mode (seed 004 Fig. 9)


def modal_analysis(cfg: AxisConfig, nut_position_m: float, *, support_scale: float = 1.0,
                   damping_b: float | None = None) -> ModalResult:
    """Non-zero modes at a nut position (distance from the fixed bearing)."""
    mech = build_mechanics(cfg, nut_position_m, support_scale=support_scale)
    mass = mech.mass_matrix()
    stiff = mech.stiffness_matrix(True)
    b = structural_damping_coefficient(cfg) if damping_b is None else damping_b
    damp = damping_matrix(mech, b, True)
    w, phi = natural_frequencies_rad_s(mass, stiff)
    freqs, zetas, shapes, defs = [], [], [], []
    springs = mech.springs + ([mech.contact] if mech.contact is not None else [])
    for i in range(len(w)):
        f = w[i] / (2 * np.pi)
        if f < RIGID_BODY_HZ:
            continue
        v = phi[:, i]
        mm = float(v @ mass @ v)
        zeta = float(v @ damp @ v) / (2 * w[i] * mm)
        # express the shape with linear and rotary bodies comparable: rotations times lead/2pi
        scale = np.array([mech.lead_m / (2 * np.pi) if bd.kind == "rot" else 1.0 for bd in mech.bodies])
        s = v * scale
        s = s / np.max(np.abs(s)) if np.max(np.abs(s)) > 0 else s
        if s[np.argmax(np.abs(s))] < 0:
            s = -s
        freqs.append(float(f))
        zetas.append(zeta)
        shapes.append([float(x) for x in s])
        # share of the modal strain energy per spring (where the mode deforms the structure; seed 004 Fig. 9)
        energy = {sp.name: 0.5 * sp.stiffness * float(mech.incidence(sp) @ v) ** 2 for sp in springs}
        total = sum(energy.values()) or 1.0
        defs.append({k: e / total for k, e in energy.items()})
    return ModalResult(
        nut_position_m=float(nut_position_m),
        natural_frequencies_hz=freqs,
        damping_ratios=zetas,
        mode_shapes=shapes,
        body_names=[bd.name for bd in mech.bodies],
        spring_deformations=defs,
    )


def first_natural_frequency_hz(cfg: AxisConfig, nut_position_m: float, support_scale: float = 1.0) -> float:
    res = modal_analysis(cfg, nut_position_m, support_scale=support_scale, damping_b=0.0)
    return res.natural_frequencies_hz[0] if res.natural_frequencies_hz else float("nan")
