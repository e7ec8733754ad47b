"""Kernel parameters of the drive and axis options that real drives have and the first kernel did not
(issue #14, "vocabulary real axes need"). Each option is a config key whose default reproduces the kernel's
behaviour before the option existed bit for bit; :func:`fill_option_parameters` writes them into the kernel's
parameter vector (called by :func:`virtualaxis.sim.simulator.build_parameters`).

* ``friction.viscous_negative_n_s_per_m``: viscous friction for -v [N s/m] (direction-dependent viscous friction).
"""

from __future__ import annotations

import numpy as np

from virtualaxis.config import AxisConfig
from virtualaxis.sim import layout as L


def viscous_negative_n_s_per_m(cfg: AxisConfig) -> float:
    """Viscous coefficient for -v [N s/m]: ``friction.viscous_negative_n_s_per_m``, or the +v coefficient when
    that is negative (the default, "same as viscous_n_s_per_m")."""
    f = cfg.friction
    return f.viscous_negative_n_s_per_m if f.viscous_negative_n_s_per_m >= 0 else f.viscous_n_s_per_m


def fill_option_parameters(pr: np.ndarray, cfg: AxisConfig) -> None:
    """Write the options' kernel parameters into ``pr`` (in place)."""
    pr[L.P_FV_NEG] = viscous_negative_n_s_per_m(cfg)
