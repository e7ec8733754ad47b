"""The [rcsa] section of an axis config: screw, lumped parts, the eight joints, mode bands, identification.

The plant loader keeps ``[rcsa]`` verbatim in ``cfg.extra["rcsa"]``; :func:`rcsa_model_from_config`
validates it here. Every value may be a bare number or ``{ value = .., source = ".." }``; errors are
:class:`~virtualaxis.config.ConfigError` naming the file and ``rcsa.<table>.<key>``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from virtualaxis.config import AxisConfig, ConfigError
from virtualaxis.rcsa import receptance as R

# eq. 25 order: phi = [k_al, k_ar, k_n, k_m, c_al, c_ar, c_n, c_m]
JOINT_KEYS = (
    "left_bearing_stiffness_n_per_m",
    "right_bearing_stiffness_n_per_m",
    "nut_stiffness_n_per_m",
    "coupling_stiffness_nm_per_rad",
    "left_bearing_damping_n_s_per_m",
    "right_bearing_damping_n_s_per_m",
    "nut_damping_n_s_per_m",
    "coupling_damping_nm_s_per_rad",
)
JOINT_SYMBOLS = ("k_al", "k_ar", "k_n", "k_m", "c_al", "c_ar", "c_n", "c_m")
JOINT_UNITS = ("N/m", "N/m", "N/m", "N m/rad", "N s/m", "N s/m", "N s/m", "N m s/rad")

SCREW_KEYS = ("length_m", "diameter_m", "youngs_modulus_pa", "shear_modulus_pa", "density_kg_m3", "lead_m")
LUMPED_KEYS = (
    "nut_segment_mass_kg",
    "nut_segment_inertia_kg_m2",
    "coupling_segment_inertia_kg_m2",
    "table_mass_kg",
    "rotor_inertia_kg_m2",
    "rotor_holding_stiffness_nm_per_rad",
    "rotor_holding_damping_nm_s_per_rad",
)
_LUMPED_MAY_BE_ZERO = ("rotor_holding_stiffness_nm_per_rad", "rotor_holding_damping_nm_s_per_rad")
IDENT_KEYS = (
    "population_per_parameter",
    "generations",
    "seed",
    "workers",
    "relative_tolerance",
    "amplitude_weight",
)


@dataclass(frozen=True)
class ScrewGeometry:
    """Ball screw between the two bearing groups (seed 002 Table A, Sec. 4.1)."""

    length_m: float
    diameter_m: float
    youngs_modulus_pa: float
    shear_modulus_pa: float
    density_kg_m3: float
    lead_m: float

    @property
    def area_m2(self) -> float:
        return math.pi * self.diameter_m**2 / 4.0

    @property
    def polar_moment_m4(self) -> float:
        """J = pi d^4 / 32 (eq. 12)."""
        return math.pi * self.diameter_m**4 / 32.0

    @property
    def lead_ratio_m_per_rad(self) -> float:
        """i_b = h / (2 pi) (eq. 21)."""
        return self.lead_m / (2.0 * math.pi)


@dataclass(frozen=True)
class LumpedParts:
    """Rigid segments F and H, worktable, rotor (seed 002 Table A) and the rotor's hold during the test."""

    nut_segment_mass_kg: float
    nut_segment_inertia_kg_m2: float
    coupling_segment_inertia_kg_m2: float
    table_mass_kg: float
    rotor_inertia_kg_m2: float
    rotor_holding_stiffness_nm_per_rad: float = 0.0
    rotor_holding_damping_nm_s_per_rad: float = 0.0


@dataclass(frozen=True)
class JointParams:
    """The eight joint parameters of eq. 25 (SI units, see JOINT_UNITS)."""

    k_al: float
    k_ar: float
    k_n: float
    k_m: float
    c_al: float
    c_ar: float
    c_n: float
    c_m: float

    def as_array(self) -> np.ndarray:
        return np.array([getattr(self, s) for s in JOINT_SYMBOLS], dtype=np.float64)

    @classmethod
    def from_array(cls, values: np.ndarray | list[float]) -> JointParams:
        vals = [float(v) for v in values]
        if len(vals) != 8:
            raise ValueError(f"need 8 joint values, got {len(vals)}")
        return cls(*vals)

    def as_dict(self) -> dict[str, float]:
        return {s: getattr(self, s) for s in JOINT_SYMBOLS}


@dataclass(frozen=True)
class IdentificationSettings:
    """Differential-evolution settings and log-scaled search bounds for eq. 25."""

    lower: JointParams
    upper: JointParams
    population_per_parameter: int = 15
    generations: int = 200
    seed: int = 0
    workers: int = 2
    relative_tolerance: float = 0.0
    amplitude_weight: float = 1.0  # weight of the amplitude terms in eq. 26 (1 = as printed)


@dataclass(frozen=True)
class RcsaModel:
    """Everything the receptance model needs except the worktable position."""

    screw: ScrewGeometry
    parts: LumpedParts
    joints: JointParams
    mode_bands_hz: tuple[tuple[float, float], ...]
    min_peak_prominence: float = 0.05
    positions_m: tuple[float, ...] = ()
    identification: IdentificationSettings | None = None
    sources: dict[str, str] = field(default_factory=dict, compare=False)

    def with_joints(self, joints: JointParams) -> RcsaModel:
        return replace(self, joints=joints)

    def parameter_vector(self, joints: JointParams | None = None) -> np.ndarray:
        """The float64 vector the compiled kernel reads (indices in :mod:`receptance`)."""
        s, q = self.screw, self.parts
        p = np.zeros(R.PARAM_COUNT, dtype=np.float64)
        p[R.P_LENGTH_M] = s.length_m
        p[R.P_AXIAL_RIGIDITY_N] = s.youngs_modulus_pa * s.area_m2
        p[R.P_AXIAL_WAVE_SLOWNESS_S_PER_M] = math.sqrt(s.density_kg_m3 / s.youngs_modulus_pa)
        p[R.P_TORSIONAL_RIGIDITY_NM2] = s.shear_modulus_pa * s.polar_moment_m4
        p[R.P_TORSIONAL_WAVE_SLOWNESS_S_PER_M] = math.sqrt(s.density_kg_m3 / s.shear_modulus_pa)
        p[R.P_LEAD_RATIO_M_PER_RAD] = s.lead_ratio_m_per_rad
        p[R.P_NUT_SEGMENT_MASS_KG] = q.nut_segment_mass_kg
        p[R.P_NUT_SEGMENT_INERTIA_KG_M2] = q.nut_segment_inertia_kg_m2
        p[R.P_COUPLING_SEGMENT_INERTIA_KG_M2] = q.coupling_segment_inertia_kg_m2
        p[R.P_TABLE_MASS_KG] = q.table_mass_kg
        p[R.P_ROTOR_INERTIA_KG_M2] = q.rotor_inertia_kg_m2
        p[R.P_ROTOR_HOLDING_STIFFNESS_NM_PER_RAD] = q.rotor_holding_stiffness_nm_per_rad
        p[R.P_ROTOR_HOLDING_DAMPING_NM_S_PER_RAD] = q.rotor_holding_damping_nm_s_per_rad
        p[R.JOINT_SLICE] = (joints or self.joints).as_array()
        return p

    def bands_array(self) -> np.ndarray:
        return np.array(self.mode_bands_hz, dtype=np.float64).reshape(-1, 2)

    def check_position(self, position_m: float, where: str = "position") -> None:
        if not (math.isfinite(position_m) and 0.0 < position_m < self.screw.length_m):
            raise ValueError(
                f"{where} {position_m!r} m is outside the screw (0 < l < {self.screw.length_m:g} m)"
            )


def _value(
    file: str, key: str, raw: Any, sources: dict, *, positive: bool, allow_zero: bool = False
) -> float:
    if isinstance(raw, dict):
        extra = set(raw) - {"value", "source", "unit"}
        if "value" not in raw or extra:
            raise ConfigError(file, key, "a table value needs exactly 'value' and optionally 'source'")
        src = raw.get("source")
        if src is not None and not isinstance(src, str):
            raise ConfigError(file, key, "source must be a string")
        if src:
            sources[key] = src
        raw = raw["value"]
    if isinstance(raw, bool) or not isinstance(raw, (int, float)):
        raise ConfigError(file, key, f"must be a number (got {raw!r})")
    val = float(raw)
    if not math.isfinite(val):
        raise ConfigError(file, key, f"must be finite (got {raw!r})")
    if positive and not (val > 0 or (allow_zero and val == 0)):
        raise ConfigError(file, key, f"must be {'>= 0' if allow_zero else '> 0'} (got {val})")
    return val


def _table(file: str, rcsa: dict, name: str, keys: tuple[str, ...], required: tuple[str, ...]) -> dict:
    raw = rcsa.get(name)
    if raw is None:
        raise ConfigError(file, f"rcsa.{name}", "missing table (required)")
    if not isinstance(raw, dict):
        raise ConfigError(file, f"rcsa.{name}", "must be a table")
    for k in raw:
        if k not in keys:
            raise ConfigError(file, f"rcsa.{name}.{k}", f"unknown key (known: {', '.join(keys)})")
    for k in required:
        if k not in raw:
            raise ConfigError(file, f"rcsa.{name}.{k}", "missing (required)")
    return raw


def _joints(file: str, rcsa: dict, name: str, sources: dict) -> JointParams:
    raw = _table(file, rcsa, name, JOINT_KEYS, JOINT_KEYS)
    vals = [_value(file, f"rcsa.{name}.{k}", raw[k], sources, positive=True) for k in JOINT_KEYS]
    return JointParams.from_array(vals)


def rcsa_model_from_dict(rcsa: Any, file: str = "<dict>") -> RcsaModel:
    """Validate the ``[rcsa]`` table (as parsed from TOML) and build an :class:`RcsaModel`."""
    file = str(file)
    if rcsa is None:
        raise ConfigError(file, "rcsa", "missing section (the receptance model needs [rcsa])")
    if not isinstance(rcsa, dict):
        raise ConfigError(file, "rcsa", "must be a table")
    known = ("screw", "parts", "joints", "modes", "identification", "positions_m")
    for k in rcsa:
        if k not in known:
            raise ConfigError(file, f"rcsa.{k}", f"unknown key (known: {', '.join(known)})")
    sources: dict[str, str] = {}
    raw = _table(file, rcsa, "screw", SCREW_KEYS, SCREW_KEYS)
    screw = ScrewGeometry(
        **{k: _value(file, f"rcsa.screw.{k}", raw[k], sources, positive=True) for k in SCREW_KEYS}
    )
    required_parts = tuple(k for k in LUMPED_KEYS if k not in _LUMPED_MAY_BE_ZERO)
    raw = _table(file, rcsa, "parts", LUMPED_KEYS, required_parts)
    parts = LumpedParts(
        **{
            k: _value(
                file, f"rcsa.parts.{k}", raw[k], sources, positive=True, allow_zero=k in _LUMPED_MAY_BE_ZERO
            )
            for k in LUMPED_KEYS
            if k in raw
        }
    )
    joints = _joints(file, rcsa, "joints", sources)
    modes = _table(file, rcsa, "modes", ("bands_hz", "min_peak_prominence"), ("bands_hz",))
    bands = _bands(file, modes["bands_hz"], sources)
    prominence = 0.05
    if "min_peak_prominence" in modes:
        prominence = _value(
            file, "rcsa.modes.min_peak_prominence", modes["min_peak_prominence"], sources, positive=True
        )
    positions: tuple[float, ...] = ()
    if "positions_m" in rcsa:
        positions = tuple(_positions(file, "rcsa.positions_m", rcsa["positions_m"], sources, screw.length_m))
    ident = None
    if "identification" in rcsa:
        ident = _identification(file, rcsa["identification"], sources)
    return RcsaModel(screw, parts, joints, bands, prominence, positions, ident, sources)


def _bands(file: str, raw: Any, sources: dict) -> tuple[tuple[float, float], ...]:
    key = "rcsa.modes.bands_hz"
    if isinstance(raw, dict):
        if "value" not in raw:
            raise ConfigError(file, key, "a table value needs 'value'")
        if isinstance(raw.get("source"), str):
            sources[key] = raw["source"]
        raw = raw["value"]
    if not isinstance(raw, list) or not raw:
        raise ConfigError(
            file, key, "must be a non-empty list of [low_hz, high_hz] pairs, one per mode order"
        )
    out = []
    prev_hi = 0.0
    for i, pair in enumerate(raw):
        if (
            not isinstance(pair, list)
            or len(pair) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in pair)
        ):
            raise ConfigError(file, f"{key}[{i}]", f"must be [low_hz, high_hz] (got {pair!r})")
        lo, hi = float(pair[0]), float(pair[1])
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo < hi):
            raise ConfigError(file, f"{key}[{i}]", f"needs 0 < low < high (got {pair!r})")
        if lo < prev_hi:
            raise ConfigError(file, f"{key}[{i}]", "bands must be sorted and must not overlap")
        prev_hi = hi
        out.append((lo, hi))
    return tuple(out)


def _positions(file: str, key: str, raw: Any, sources: dict, length_m: float) -> list[float]:
    if isinstance(raw, dict):
        if isinstance(raw.get("source"), str):
            sources[key] = raw["source"]
        raw = raw.get("value")
    if not isinstance(raw, list) or not raw:
        raise ConfigError(file, key, "must be a non-empty list of positions in metres")
    out = []
    for v in raw:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ConfigError(file, key, f"must hold numbers (got {v!r})")
        if not 0 < v < length_m:
            raise ConfigError(file, key, f"position {v} m is outside the screw (0 < l < {length_m:g} m)")
        out.append(float(v))
    if len(set(out)) != len(out):
        raise ConfigError(file, key, "duplicate position")
    return out


def _identification(file: str, raw: Any, sources: dict) -> IdentificationSettings:
    if not isinstance(raw, dict):
        raise ConfigError(file, "rcsa.identification", "must be a table")
    for k in raw:
        if k not in (*IDENT_KEYS, "lower", "upper"):
            raise ConfigError(file, f"rcsa.identification.{k}", "unknown key")
    lower = _joints(file, raw, "lower", sources) if "lower" in raw else None
    upper = _joints(file, raw, "upper", sources) if "upper" in raw else None
    if lower is None or upper is None:
        missing = "lower" if lower is None else "upper"
        raise ConfigError(file, f"rcsa.identification.{missing}", "missing table (required)")
    for sym, key, lo, hi in zip(JOINT_SYMBOLS, JOINT_KEYS, lower.as_array(), upper.as_array(), strict=True):
        if not lo < hi:
            raise ConfigError(
                file, f"rcsa.identification.upper.{key}", f"must exceed lower ({sym}: {lo} >= {hi})"
            )
    kw: dict[str, Any] = {}
    for k in ("population_per_parameter", "generations", "seed", "workers"):
        if k in raw:
            v = raw[k]
            v = v.get("value") if isinstance(v, dict) else v
            if isinstance(v, bool) or not isinstance(v, int) or (k != "seed" and v < 1):
                raise ConfigError(file, f"rcsa.identification.{k}", f"must be a positive integer (got {v!r})")
            kw[k] = v
    if "amplitude_weight" in raw:
        kw["amplitude_weight"] = _value(
            file,
            "rcsa.identification.amplitude_weight",
            raw["amplitude_weight"],
            sources,
            positive=True,
            allow_zero=True,
        )
    if "relative_tolerance" in raw:
        kw["relative_tolerance"] = _value(
            file,
            "rcsa.identification.relative_tolerance",
            raw["relative_tolerance"],
            sources,
            positive=True,
            allow_zero=True,
        )
    return IdentificationSettings(lower=lower, upper=upper, **kw)


def rcsa_model_from_config(cfg: AxisConfig) -> RcsaModel:
    """The validated receptance model of an axis config (``cfg.extra["rcsa"]``)."""
    return rcsa_model_from_dict(cfg.extra.get("rcsa"), cfg.path)
