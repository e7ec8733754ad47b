"""Contour error of two-axis moves: the metric against closed forms, pairing, and an end-to-end report."""

import json

import background
import numpy as np
import pytest

from virtualaxis.diagnosis.contour import contour_error, contour_pairs


def test_contour_error_of_a_circle_is_the_radial_deviation_whatever_the_lag():
    t = np.linspace(0, 2 * np.pi, 20000)
    r = 0.05
    xc, yc = r * np.cos(t), r * np.sin(t)
    # measured: radius 7 um larger and lagging 0.3 rad along the path
    lag = t - 0.3
    xm, ym = (r + 7e-6) * np.cos(lag), (r + 7e-6) * np.sin(lag)
    e = contour_error(xc, yc, xm[2000:], ym[2000:])
    assert np.max(np.abs(e - 7e-6)) < 1e-9
    # a point inside the circle
    assert contour_error(xc, yc, np.array([0.0]), np.array([r - 3e-6]))[0] == pytest.approx(3e-6, abs=1e-9)


def test_pairs_need_matching_names_and_time_axes():
    t = np.arange(5.0)
    assert contour_pairs(["circ_x", "circ_y", "other"], [t, t, t]) == [(0, 1)]
    assert contour_pairs(["circ_x", "circ_y"], [t, t + 1]) == []
    assert contour_pairs(["a_x", "b_y"], [t, t]) == []


def diagnose_circle(tmp_path) -> dict:
    """``virtualaxis diagnose`` on the X/Y traces of two circles of an axis pair with backlash withheld (a
    background job of the suite: tests/background.py)."""
    import contextlib
    import io

    from plant_helpers import config_with

    from virtualaxis.cli.main import main
    from virtualaxis.sim import simulate_profile
    from virtualaxis.sim.trace_io import write_trace_csv

    truth = config_with({"sensors": {"position_noise_m": 1e-7}})
    nominal = truth.replace(backlash={"enabled": False, "gap_m": 0.0})
    nom_path = tmp_path / "nominal.toml"
    nom_path.write_text(nominal.to_toml("nominal"))
    paths = []
    for spec, stem in (("circle:radius_mm=20,omega_rad_min=120", "fast"), ("circle:radius_mm=20,omega_rad_min=60",
                                                                          "slow")):
        for axis, tr in simulate_profile(truth, spec, 2.0, seed=3).items():
            p = tmp_path / f"{stem}_{axis}.csv"
            write_trace_csv(p, tr)
            paths.append(p)
    out = tmp_path / "out"
    fit = [str(p) for p in paths if p.name.startswith("slow")]
    hold = [str(p) for p in paths if p.name.startswith("fast")]
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        rc = main(["diagnose", "--config", str(nom_path), *fit, "--holdout", *hold, "--out", str(out),
                   "--effects", "backlash,coulomb_friction", "--no-hybrid"])
    return {"rc": rc, "stderr": err.getvalue(), "out": out}


@pytest.mark.background("diagnose_circle")
def test_diagnose_reports_contour_error_for_a_circle(request):
    job = background.result(request.config, "diagnose_circle")
    assert job["rc"] == 0, job["stderr"]
    out = job["out"]
    rep = json.loads((out / "report.json").read_text())
    assert len(rep["contour"]) == 2
    for c in rep["contour"]:
        assert c["measured_max_m"] > 5e-6
        nom, cal = c["models"]["nominal"], c["models"]["calibrated"]
        assert cal["prediction_error_rms_m"] < nom["prediction_error_rms_m"]
    assert "Contour error of two-axis moves" in (out / "report.html").read_text()
