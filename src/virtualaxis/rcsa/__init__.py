"""Receptance-coupling FRF model of the ball-screw feed drive (seed 002) and joint identification.

Quick use::

    from virtualaxis.config import load_axis_config
    from virtualaxis.rcsa import rcsa_model_from_config, table_frf_m_per_n, predict_modes

    model = rcsa_model_from_config(load_axis_config("configs/seed002-usst.toml"))
    h = table_frf_m_per_n(model, 1.0, np.geomspace(5, 1000, 2000))   # h_all-6a6a, complex [m/N]
    modes = predict_modes(model, [0.6, 1.0, 1.6])                      # per band, NaN = gap

See docs/rcsa.md.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from virtualaxis.lazy import lazy_exports

if TYPE_CHECKING:
    from virtualaxis.rcsa.identify import (
        IdentificationResult,
        MeasuredModes,
        identify_joints,
        overall_error,
        predict_modes,
        relative_errors,
    )
    from virtualaxis.rcsa.params import JointParams, RcsaModel, rcsa_model_from_config, rcsa_model_from_dict

# imported on first use (virtualaxis.lazy): rcsa.params loads without scipy.optimize (rcsa.identify)
__getattr__, __dir__ = lazy_exports(__name__, {
    **{n: "virtualaxis.rcsa.identify" for n in ("IdentificationResult", "MeasuredModes", "identify_joints",
                                                "overall_error", "predict_modes", "relative_errors")},
    **{n: "virtualaxis.rcsa.params" for n in ("JointParams", "RcsaModel", "rcsa_model_from_config",
                                              "rcsa_model_from_dict")},
}, globals())


def table_frf_m_per_n(
    model: RcsaModel, position_m: float, freq_hz: np.ndarray, joints: JointParams | None = None
) -> np.ndarray:
    """The coupled table FRF h_all-6a6a (eq. 24) [m/N] at nut position ``position_m`` on ``freq_hz``."""
    from virtualaxis.rcsa.receptance import table_frf

    model.check_position(float(position_m))
    f = np.ascontiguousarray(freq_hz, dtype=np.float64)
    if f.ndim != 1 or not np.all(np.isfinite(f)) or np.any(f <= 0):
        raise ValueError("freq_hz must be a 1-D array of finite frequencies > 0")
    out = np.empty(f.size, dtype=np.complex128)
    table_frf(f, float(position_m), model.parameter_vector(joints), out)
    return out


__all__ = [
    "IdentificationResult",
    "JointParams",
    "MeasuredModes",
    "RcsaModel",
    "identify_joints",
    "overall_error",
    "predict_modes",
    "rcsa_model_from_config",
    "rcsa_model_from_dict",
    "relative_errors",
    "table_frf_m_per_n",
]
