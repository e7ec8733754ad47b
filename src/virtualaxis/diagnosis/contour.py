"""Contour error of two-axis moves (seed 000 Table 4): where the gap shows as a deviation from the path.

Two traces form a pair when their names differ only by a trailing ``_x`` / ``_y`` (as ``virtualaxis simulate``
writes a circle) and they share the time axis. The contour error of a position sample is its distance to the
commanded path (the polyline of the commanded X/Y samples), found by a nearest-neighbour search and the
distance to the two adjacent segments, so it is exact for the polyline whatever the lag along the path.
"""

from __future__ import annotations

import re

import numpy as np

POSITION_CHANNELS = ("pos_meas", "pos_fb")


def contour_pairs(names: list[str], times: list[np.ndarray]) -> list[tuple[int, int]]:
    """Index pairs (x, y) of traces named ``<stem>_x`` / ``<stem>_y`` with the same time axis."""
    pat = re.compile(r"^(.*)[_-]([xy])$", re.IGNORECASE)
    by_stem: dict[str, dict[str, int]] = {}
    for i, name in enumerate(names):
        m = pat.match(name)
        if m:
            by_stem.setdefault(m.group(1), {})[m.group(2).lower()] = i
    pairs = []
    for axes in by_stem.values():
        if "x" in axes and "y" in axes:
            ix, iy = axes["x"], axes["y"]
            tx, ty = times[ix], times[iy]
            if tx.shape == ty.shape and np.allclose(tx, ty, rtol=0, atol=1e-9):
                pairs.append((ix, iy))
    return pairs


def contour_error(x_cmd: np.ndarray, y_cmd: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Distance [m] of each point (x, y) to the commanded polyline (x_cmd, y_cmd)."""
    from scipy.spatial import cKDTree

    path = np.column_stack([x_cmd, y_cmd])
    pts = np.column_stack([x, y])
    # drop repeated command points (standstill) so every segment has a length
    keep = np.ones(len(path), bool)
    keep[1:] = np.any(np.diff(path, axis=0) != 0, axis=1)
    path = path[keep]
    if len(path) < 2:
        return np.hypot(x - x_cmd[0], y - y_cmd[0])
    _, j = cKDTree(path).query(pts)
    best = np.full(len(pts), np.inf)
    for a_idx in (j - 1, j):
        a_idx = np.clip(a_idx, 0, len(path) - 2)
        a, b = path[a_idx], path[a_idx + 1]
        ab = b - a
        u = np.clip(np.einsum("ij,ij->i", pts - a, ab) / np.einsum("ij,ij->i", ab, ab), 0.0, 1.0)
        d = np.hypot(*(pts - (a + u[:, None] * ab)).T)
        best = np.minimum(best, d)
    return best


def contour_summary(name_x: str, name_y: str, x_cmd, y_cmd, measured: tuple, predictions: dict[str, tuple]) -> dict:
    """Measured and predicted contour errors of one pair; ``predictions`` maps a model label to (x, y)."""
    e_meas = contour_error(x_cmd, y_cmd, *measured)
    out = {"traces": [name_x, name_y], "measured_max_m": float(np.max(e_meas)),
           "measured_rms_m": float(np.sqrt(np.mean(e_meas**2))), "models": {}}
    for label, (px, py) in predictions.items():
        e = contour_error(x_cmd, y_cmd, px, py)
        out["models"][label] = {
            "predicted_max_m": float(np.max(e)),
            "predicted_rms_m": float(np.sqrt(np.mean(e**2))),
            # how well the model predicts the contour error sample by sample (seed 000 Fig. 16)
            "prediction_error_max_m": float(np.max(np.abs(e - e_meas))),
            "prediction_error_rms_m": float(np.sqrt(np.mean((e - e_meas) ** 2))),
        }
    return out


def contour_report(tds: list, preds_by_model: dict[str, list[dict]]) -> list[dict]:
    """Contour errors of every X/Y pair among the traces, for each model's predictions."""
    pairs = contour_pairs([td.name for td in tds], [td.t for td in tds])
    res = []
    for ix, iy in pairs:
        ch = next((c for c in POSITION_CHANNELS if c in tds[ix].measured and c in tds[iy].measured), None)
        if ch is None:
            continue
        preds = {}
        for label, preds_list in preds_by_model.items():
            px, py = preds_list[ix].get(ch), preds_list[iy].get(ch)
            if px is not None and py is not None:
                preds[label] = (px, py)
        s = contour_summary(tds[ix].name, tds[iy].name, tds[ix].pos_cmd, tds[iy].pos_cmd,
                            (tds[ix].measured[ch], tds[iy].measured[ch]), preds)
        s["channel"] = ch
        res.append(s)
    return res
