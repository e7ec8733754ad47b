"""Command profiles from SPEC strings.

- ``sine:stroke_mm=100,feed_mm_min=6000[,phase=cos|sin]`` — seed 000's tests: x = A (1 - cos w t) (from rest,
  default) or A sin w t, A = stroke/2, peak feed = A w.
- ``ptp:distance_mm=50,feed_mm_min=10000,accel_m_s2=2,jerk_m_s3=50[,dwell_s=0.2]`` — jerk-limited point-to-point
  move (7-segment S-curve), then a dwell.
- ``step:distance_um=10[,at_s=0.01]`` — a position step.
- ``chirp:amplitude_um=5,f0_hz=1,f1_hz=500[,sweep=log|linear]`` — swept sine over the whole duration.
- ``circle:radius_mm=50,omega_rad_min=120`` — two axes: x = R (cos w t - 1), y = R sin w t.
- ``file:moves.csv`` — a CSV with ``t`` [s] and ``pos`` [m] (one axis) or ``x``, ``y`` [m] columns, linearly
  interpolated.

Every profile is checked against the axis limits (velocity, acceleration, travel): a profile beyond them is
rejected with a :class:`ProfileError` saying which limit and by how much. Excitation signals (``step``, small
``chirp``) and recorded ``file`` commands are checked for velocity and travel only, as a drive's measuring
function is: their acceleration is not a path acceleration.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from virtualaxis.config import AxisConfig
from virtualaxis.config.errors import InputError


class ProfileError(InputError):
    """A profile SPEC that cannot be parsed or does not fit the axis."""

    def __init__(self, spec: str, message: str):
        ValueError.__init__(self, f"profile '{spec}': {message}")
        self.file, self.row, self.column = spec, None, None


@dataclass
class Profile:
    """A command: positions (and analytic velocity/acceleration) per axis as functions of time."""

    spec: str
    axes: tuple[str, ...]
    natural_duration_s: float
    fn: object = field(repr=False)  # t [s] (, duration [s]) -> per axis (position, velocity, acceleration)
    #: the move file a ``file:`` profile reads (an output must never overwrite it)
    source_path: str | None = None
    #: highest frequency in the command [Hz] (chirp), checked against the position cycle's Nyquist frequency
    max_frequency_hz: float = 0.0
    #: an event that must happen inside the run (the step time) [s]
    event_s: float | None = None

    def check_duration(self, duration_s: float) -> None:
        """Refuse a run that ends before the profile's event (a step at 1e9 s in a 0.5 s run)."""
        if self.event_s is not None and self.event_s >= duration_s:
            raise ProfileError(self.spec, f"the step at {self.event_s:g} s lies after the end of the "
                                          f"{duration_s:g} s run (the command would never move)")

    def sample(self, t: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Position [m], velocity [m/s], acceleration [m/s^2] per axis at times ``t``."""
        return self.fn(np.asarray(t, dtype=float))


def _kv(spec: str, body: str, required: tuple[str, ...], optional: dict) -> dict:
    vals: dict = dict(optional)
    seen = set()
    for part in filter(None, (p.strip() for p in body.split(","))):
        if "=" not in part:
            raise ProfileError(spec, f"expected key=value, got '{part}'")
        k, v = (s.strip() for s in part.split("=", 1))
        if k in seen:
            raise ProfileError(spec, f"parameter '{k}' given twice")
        if k not in required and k not in optional:
            raise ProfileError(spec, f"unknown parameter '{k}' (expected {', '.join(required + tuple(optional))})")
        if isinstance(optional.get(k), str):
            vals[k] = v
        else:
            try:
                vals[k] = float(v)
            except ValueError:
                raise ProfileError(spec, f"parameter '{k}' must be a number, got '{v}'") from None
            if not math.isfinite(vals[k]):
                raise ProfileError(spec, f"parameter '{k}' must be finite")
            if vals[k] != 0 and abs(vals[k]) < 2.2250738585072014e-308:
                raise ProfileError(spec, f"parameter '{k}' = {v} is a subnormal number (below 2.2e-308 in "
                                         "magnitude): a typing error; give 0 or a real value")
        seen.add(k)
    missing = [k for k in required if k not in seen]
    if missing:
        raise ProfileError(spec, f"missing parameter(s) {', '.join(missing)}")
    return vals


def _positive(spec: str, vals: dict, *keys: str) -> None:
    for k in keys:
        if not vals[k] > 0:
            raise ProfileError(spec, f"parameter '{k}' must be > 0 (got {vals[k]:g})")


def scurve_rest_to_rest(distance_m: float, v_max: float, a_max: float, j_max: float):
    """Jerk-limited rest-to-rest profile (double-S, Biagiotti & Melchiorri 3.4). Returns ``fn(t) -> (p, v, a)``
    and the move time."""
    sgn = 1.0 if distance_m >= 0 else -1.0
    h = abs(distance_m)
    if h == 0:
        return (lambda t: (np.zeros_like(t), np.zeros_like(t), np.zeros_like(t))), 0.0
    # acceleration phase
    if v_max * j_max < a_max**2:
        tj = math.sqrt(v_max / j_max)
        ta = 2 * tj
    else:
        tj = a_max / j_max
        ta = tj + v_max / a_max
    tv = h / v_max - ta
    if tv < 0:  # v_max is not reached (B&M eq. 3.26 with v0 = v1 = 0)
        tv = 0.0
        tj = a_max / j_max
        ta = (a_max**2 / j_max + math.sqrt(a_max**4 / j_max**2 + 4 * h * a_max)) / (2 * a_max)
        if ta < 2 * tj:  # a_max is not reached either
            tj = (h / (2 * j_max)) ** (1.0 / 3.0)
            ta = 2 * tj
    # build the piecewise-constant jerk sequence and integrate exactly
    tj1 = tj
    seq = [(tj1, j_max), (ta - 2 * tj1, 0.0), (tj1, -j_max), (tv, 0.0), (tj1, -j_max), (ta - 2 * tj1, 0.0),
           (tj1, j_max)]
    seq = [(d, j) for d, j in seq if d > 1e-12]
    # exact integration of each segment's start state
    starts = []
    p = v = a = 0.0
    t0 = 0.0
    for d, j in seq:
        starts.append((t0, p, v, a, j))
        p = p + v * d + a * d * d / 2 + j * d**3 / 6
        v = v + a * d + j * d * d / 2
        a = a + j * d
        t0 += d
    total = t0
    scale = h / p if p > 0 else 1.0  # remove round-off so the end point is exact

    def fn(t):
        t = np.asarray(t, dtype=float)
        pos = np.full_like(t, h)
        vel = np.zeros_like(t)
        acc = np.zeros_like(t)
        for i, (ts, ps, vs, as_, j) in enumerate(starts):
            te = starts[i + 1][0] if i + 1 < len(starts) else total
            m = (t >= ts) & (t < te)
            dt = t[m] - ts
            pos[m] = ps + vs * dt + as_ * dt**2 / 2 + j * dt**3 / 6
            vel[m] = vs + as_ * dt + j * dt**2 / 2
            acc[m] = as_ + j * dt
        pos[t < 0] = 0.0
        return sgn * pos * scale, sgn * vel * scale, sgn * acc * scale

    return fn, total


def parse_profile(spec: str, cfg: AxisConfig | None = None, start_position_m: float = 0.0) -> Profile:
    """Parse a SPEC string (see module doc). ``cfg`` supplies the limits checked by :func:`check_limits`."""
    if ":" not in spec:
        raise ProfileError(spec, "expected KIND:params, e.g. sine:stroke_mm=100,feed_mm_min=6000")
    kind, body = spec.split(":", 1)
    kind = kind.strip().lower()
    x0 = start_position_m
    if kind == "sine":
        v = _kv(spec, body, ("stroke_mm", "feed_mm_min"), {"phase": "cos"})
        _positive(spec, v, "stroke_mm", "feed_mm_min")
        if v["phase"] not in ("cos", "sin"):
            raise ProfileError(spec, "phase must be cos or sin")
        amp = v["stroke_mm"] / 2000.0
        vmax = v["feed_mm_min"] / 60000.0
        w = vmax / amp
        if v["phase"] == "cos":
            def fn(t):
                return {"x": (x0 + amp * (1 - np.cos(w * t)), amp * w * np.sin(w * t), amp * w * w * np.cos(w * t))}
        else:
            def fn(t):
                return {"x": (x0 + amp * np.sin(w * t), amp * w * np.cos(w * t), -amp * w * w * np.sin(w * t))}
        return Profile(spec, ("x",), 2 * math.pi / w, fn)
    if kind == "ptp":
        v = _kv(spec, body, ("distance_mm", "feed_mm_min", "accel_m_s2", "jerk_m_s3"), {"dwell_s": 0.2})
        _positive(spec, v, "feed_mm_min", "accel_m_s2", "jerk_m_s3")
        sfn, total = scurve_rest_to_rest(v["distance_mm"] / 1000.0, v["feed_mm_min"] / 60000.0, v["accel_m_s2"],
                                         v["jerk_m_s3"])

        def fn(t):
            p, vv, a = sfn(t)
            return {"x": (x0 + p, vv, a)}

        if not v["dwell_s"] >= 0:
            raise ProfileError(spec, f"parameter 'dwell_s' must be >= 0 (got {v['dwell_s']:g})")
        return Profile(spec, ("x",), total + v["dwell_s"], fn)
    if kind == "step":
        v = _kv(spec, body, ("distance_um",), {"at_s": 0.01})
        if not v["at_s"] >= 0:
            raise ProfileError(spec, f"parameter 'at_s' must be >= 0 (got {v['at_s']:g})")
        if v["distance_um"] == 0:
            raise ProfileError(spec, "parameter 'distance_um' must not be 0 (a step of 0 moves nothing; negative "
                                     "steps are allowed)")
        d = v["distance_um"] * 1e-6

        def fn(t):
            p = np.where(t >= v["at_s"], x0 + d, x0)
            return {"x": (p, np.zeros_like(t), np.zeros_like(t))}

        return Profile(spec, ("x",), v["at_s"] + 0.2, fn, event_s=v["at_s"])
    if kind == "chirp":
        v = _kv(spec, body, ("amplitude_um", "f0_hz", "f1_hz"), {"sweep": "log", "duration_s": 0.0})
        _positive(spec, v, "amplitude_um", "f0_hz", "f1_hz")
        if v["sweep"] not in ("log", "linear"):
            raise ProfileError(spec, "sweep must be log or linear")
        amp = v["amplitude_um"] * 1e-6
        f0, f1 = v["f0_hz"], v["f1_hz"]
        if v["duration_s"] < 0:
            raise ProfileError(spec, f"parameter 'duration_s' must be >= 0 (got {v['duration_s']:g})")
        dur_default = v["duration_s"] if v["duration_s"] > 0 else 10.0
        prof = Profile(spec, ("x",), dur_default, None, max_frequency_hz=max(f0, f1))

        def fn(t, dur=None):
            T = dur or prof.natural_duration_s
            if f0 == f1:  # the limit of both sweeps: a plain sine
                ph = 2 * math.pi * f0 * t
                f = np.full_like(t, f0)
            elif v["sweep"] == "linear":
                k = (f1 - f0) / T
                ph = 2 * math.pi * (f0 * t + k * t * t / 2)
                f = f0 + k * t
            else:
                k = math.log(f1 / f0) / T
                ph = 2 * math.pi * f0 * (np.exp(k * t) - 1) / k
                f = f0 * np.exp(k * t)
            w = 2 * math.pi * f
            p = amp * np.sin(ph)
            vel = amp * w * np.cos(ph)
            acc = -amp * w * w * np.sin(ph)
            return {"x": (x0 + p, vel, acc)}

        prof.fn = fn
        return prof
    if kind == "circle":
        v = _kv(spec, body, ("radius_mm", "omega_rad_min"), {})
        _positive(spec, v, "radius_mm", "omega_rad_min")
        rad = v["radius_mm"] / 1000.0
        w = v["omega_rad_min"] / 60.0

        def fn(t):
            c, s = np.cos(w * t), np.sin(w * t)
            return {
                "x": (x0 + rad * (c - 1), -rad * w * s, -rad * w * w * c),
                "y": (x0 + rad * s, rad * w * c, -rad * w * w * s),
            }

        return Profile(spec, ("x", "y"), 2 * math.pi / w, fn)
    if kind == "file":
        return _file_profile(spec, body.strip(), x0)
    raise ProfileError(spec, f"unknown kind '{kind}' (sine, ptp, step, chirp, circle, file)")


def _file_profile(spec: str, path: str, x0: float) -> Profile:
    """A ``file:`` move list: CSV with ``t`` and ``pos`` (or ``x`` and ``y``), UTF-8 (a BOM is accepted)."""
    from array import array

    p = Path(path)
    if not path:
        raise ProfileError(spec, "file: needs a file name, e.g. file:moves.csv")
    if not p.exists():
        raise InputError(path, "file not found")
    if p.is_dir():
        raise InputError(path, "is a folder, not a CSV file")
    if not p.is_file():
        raise InputError(path, "not a regular file (a device, pipe or socket); give a CSV file")
    values = array("d")
    rown = 1
    try:
        with p.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh)
            try:
                header = [h.strip() for h in next(reader)]
            except StopIteration:
                raise InputError(path, "empty file (a header row t,pos or t,x,y is required)", row=1) from None
            dups = sorted({h for h in header if header.count(h) > 1 and h})
            if dups:
                raise InputError(path, "duplicate column name", row=1, column=dups[0])
            if "t" not in header:
                raise InputError(path, f"missing required column (header: {', '.join(header)})", row=1, column="t")
            axes = ("x", "y") if ("x" in header and "y" in header) else ("pos",) if "pos" in header else ()
            if not axes:
                raise InputError(path, "need a 'pos' column (one axis) or 'x' and 'y' columns", row=1)
            cols = {name: header.index(name) for name in ("t",) + axes}
            last_t = -math.inf
            for rown, row in enumerate(reader, start=2):
                if not row or all(not c.strip() for c in row):
                    continue
                for name, ci in cols.items():
                    cell = row[ci].strip() if ci < len(row) else ""
                    try:
                        val = float(cell)
                    except ValueError:
                        what = "missing value (the row is short)" if ci >= len(row) else f"not a number: {cell!r}"
                        raise InputError(path, what, row=rown, column=name) from None
                    if not math.isfinite(val):
                        raise InputError(path, f"not a finite number: {cell!r}", row=rown, column=name)
                    if name == "t":
                        if val <= last_t:
                            raise InputError(path, f"time must increase strictly ({last_t:g} then {val:g})",
                                             row=rown, column="t")
                        last_t = val
                    values.append(val)
    except UnicodeDecodeError:
        from virtualaxis.config.errors import first_non_utf8_line

        bad_row, byte = first_non_utf8_line(p)
        raise InputError(path, f"not UTF-8 text (byte 0x{byte:02x})", row=bad_row) from None
    except csv.Error as exc:
        raise InputError(path, f"not a readable CSV file ({exc})", row=rown + 1) from None
    width = len(cols)
    if len(values) < 2 * width:
        raise InputError(path, "need at least two samples")
    data = np.frombuffer(values, dtype=float).reshape(-1, width)
    t_data = data[:, 0] - data[0, 0]
    names = ("x", "y") if axes == ("x", "y") else ("x",)

    def fn(t):
        res = {}
        for k, name in enumerate(names):
            pos = np.interp(t, t_data, data[:, 1 + k])
            vel = np.gradient(pos, t) if len(t) > 1 else np.zeros_like(t)
            acc = np.gradient(vel, t) if len(t) > 1 else np.zeros_like(t)
            res[name] = (pos, vel, acc)
        return res

    return Profile(spec, names, float(t_data[-1]), fn, source_path=str(p))


def check_limits(profile: Profile, cfg: AxisConfig, duration_s: float, cycle_s: float) -> dict:
    """Reject a profile beyond the axis limits; returns the peak figures for the summary."""
    t = np.arange(0.0, duration_s + cycle_s / 2, cycle_s)
    lim = cfg.limits
    peaks = {}
    nyquist = 0.5 / cycle_s
    if profile.max_frequency_hz > nyquist:
        raise ProfileError(profile.spec, f"frequency {profile.max_frequency_hz:g} Hz is above the Nyquist "
                                         f"frequency {nyquist:g} Hz of the {cycle_s:g} s position cycle "
                                         "(the command would alias)")
    for name, (p, v, a) in sample_profile(profile, t, duration_s).items():
        for arr, what in ((p, "position"), (v, "velocity"), (a, "acceleration")):
            bad = ~np.isfinite(arr)
            if bad.any():
                raise ProfileError(profile.spec, f"axis {name}: non-finite {what} at t = "
                                                 f"{float(t[np.flatnonzero(bad)[0]]):g} s")
        vmax, amax = float(np.max(np.abs(v))), float(np.max(np.abs(a)))
        if v.size > 1:  # what the drive is commanded per position cycle: a jerk phase shorter than one cycle is
            # not seen in the sampled acceleration (ptp accel 1e9, jerk 1e12: 0.1 m/s within one 1 ms cycle)
            amax = max(amax, float(np.max(np.abs(np.diff(v)))) / cycle_s)
        pmin, pmax = float(np.min(p)), float(np.max(p))
        if vmax > lim.max_velocity_m_s * (1 + 1e-9):
            raise ProfileError(profile.spec, f"axis {name}: peak velocity {vmax:.4g} m/s exceeds "
                                             f"limits.max_velocity_m_s = {lim.max_velocity_m_s:g} m/s")
        if amax > lim.max_acceleration_m_s2 * (1 + 1e-9) and not profile.spec.startswith(("step", "chirp", "file")):
            raise ProfileError(profile.spec, f"axis {name}: peak acceleration {amax:.4g} m/s^2 exceeds "
                                             f"limits.max_acceleration_m_s2 = {lim.max_acceleration_m_s2:g} m/s^2")
        if pmin < lim.travel_min_m or pmax > lim.travel_max_m:
            raise ProfileError(profile.spec, f"axis {name}: travel {pmin:.4g}..{pmax:.4g} m leaves the software limits "
                                             f"{lim.travel_min_m:g}..{lim.travel_max_m:g} m")
        peaks[name] = {"peak_velocity_m_s": vmax, "peak_acceleration_m_s2": amax, "min_position_m": pmin,
                       "max_position_m": pmax}
    return peaks


def sample_profile(profile: Profile, t: np.ndarray, duration_s: float):
    """Sample, passing the requested duration to profiles that scale with it (chirp)."""
    fn = profile.fn
    try:
        return fn(t, duration_s)  # type: ignore[misc]
    except TypeError:
        return fn(t)  # type: ignore[misc]
