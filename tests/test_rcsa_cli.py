"""``virtualaxis rcsa`` and ``virtualaxis identify-joints`` end to end through the real CLI entry point."""

from __future__ import annotations

import json
from pathlib import Path

import background
import numpy as np
import pytest
import tomllib

from virtualaxis.cli.main import main
from virtualaxis.config import load_axis_config
from virtualaxis.rcsa.identify import predict_modes
from virtualaxis.rcsa.params import JointParams, rcsa_model_from_config

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "seed002-usst.toml"
TRUTH = JointParams(4.28e7, 2.94e7, 7.09e8, 880.0, 100.0, 100.0, 500.0, 0.1)  # Table 3, k_m read as in the config


def rcsa_json_and_plots(tmp_path: Path) -> dict:
    """``virtualaxis rcsa`` at six nut positions with JSON, plots and the FE check (a background job of the suite:
    tests/background.py): exit status, output and the output folder."""
    import contextlib
    import io

    out = tmp_path / "out.json"
    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        rc = main(["rcsa", "--config", str(CONFIG), "--positions", "0.6,0.8,1.0,1.3,1.6,1.9", "--json", str(out),
                   "--plot", str(tmp_path / "plots"), "--fe-check"])
    return {"rc": rc, "stdout": text.getvalue(), "out": tmp_path}


@pytest.mark.background("rcsa_json_and_plots")
def test_rcsa_json_and_plots(request):
    job = background.result(request.config, "rcsa_json_and_plots")
    tmp_path = job["out"]
    out = tmp_path / "out.json"
    assert job["rc"] == 0
    doc = json.loads(out.read_text())
    assert [r["position_m"] for r in doc["results"]] == [0.6, 0.8, 1.0, 1.3, 1.6, 1.9]
    first = doc["results"][0]
    assert len(first["natural_frequencies_hz"]) == 4 and len(first["amplitudes_m_per_n"]) == 4
    assert 23.0 < first["natural_frequencies_hz"][0] < 25.0
    # Table 3's large nut damping hides modes 3 and 4 in the FRF: reported as gaps (null), not numbers
    assert first["natural_frequencies_hz"][2] is None and first["amplitudes_m_per_n"][2] is None
    assert len(list((tmp_path / "plots").glob("frf_*.png"))) == 6
    assert "no peak in their band" in job["stdout"]


@pytest.mark.parametrize(
    "positions, words",
    [
        ("0.6,,1.0", "not a number"),
        ("0.6,nan", "not a finite number"),
        ("0.6,0.6", "duplicate position"),
        ("2.7", "outside the screw"),
    ],
)
def test_rcsa_bad_positions_exit_2_with_one_line(positions, words, capsys):
    assert main(["rcsa", "--config", str(CONFIG), "--positions", positions]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and words in err[0]


def test_rcsa_config_without_rcsa_section(tmp_path, capsys):
    text = CONFIG.read_text().split("\n[rcsa]\n")[0]
    cfg = tmp_path / "no_rcsa.toml"
    cfg.write_text(text)
    assert main(["rcsa", "--config", str(cfg), "--positions", "1.0"]) == 2
    assert "rcsa: missing section" in capsys.readouterr().err


def _mode_table(tmp_path: Path) -> Path:
    model = rcsa_model_from_config(load_axis_config(CONFIG))
    rows = ["position_m,order,freq_hz,amplitude_m_per_n"]
    for pr in predict_modes(model, [0.6, 0.8, 1.0, 1.3], TRUTH):
        for q, (f, a) in enumerate(zip(pr.natural_frequencies_hz, pr.amplitudes_m_per_n, strict=True)):
            rows.append(f"{pr.position_m},{q + 1},{'' if np.isnan(f) else f},{'' if np.isnan(a) else a}")
    p = tmp_path / "modes.csv"
    p.write_text("\n".join(rows) + "\n")
    return p


def test_identify_joints_writes_json_and_a_loadable_config(tmp_path, capsys):
    modes = _mode_table(tmp_path)
    out, new = tmp_path / "ident.json", tmp_path / "new.toml"
    rc = main(
        [
            "identify-joints",
            "--config",
            str(CONFIG),
            "--modes",
            str(modes),
            "--train-positions",
            "0.6,1.0",
            "--validate-positions",
            "0.8,1.3",
            "--json",
            str(out),
            "--write-config",
            str(new),
            "--generations",
            "8",
            "--population",
            "5",
            "--workers",
            "1",
            "--seed",
            "2",
        ]
    )
    assert rc == 0
    doc = json.loads(out.read_text())
    assert set(doc["identified"]) == {"k_al", "k_ar", "k_n", "k_m", "c_al", "c_ar", "c_n", "c_m"}
    assert doc["objective"] >= 0 and doc["generations"] == 8
    assert [r["position_m"] for r in doc["train"]] == [0.6, 1.0]
    assert [r["position_m"] for r in doc["validate"]] == [0.8, 1.3]
    assert len(doc["validate"][0]["frequency_relative_errors"]) == 4
    # the written config: identified joints in [rcsa.joints] and the plant stiffnesses, the rest unchanged
    cfg = load_axis_config(new)
    model = rcsa_model_from_config(cfg)
    assert model.joints.k_n == pytest.approx(doc["identified"]["k_n"], rel=1e-5)
    assert cfg.mechanics.nut_contact_stiffness_n_per_m == pytest.approx(doc["identified"]["k_n"], rel=1e-5)
    assert cfg.sources["mechanics.nut_contact_stiffness_n_per_m"].startswith("identified ")
    old_lines, new_lines = CONFIG.read_text().splitlines(), new.read_text().splitlines()
    assert len(old_lines) == len(new_lines)
    changed = [i for i, (a, b) in enumerate(zip(old_lines, new_lines, strict=True)) if a != b]
    assert len(changed) == 8 + 3
    assert tomllib.loads(new.read_text())["control"] == tomllib.loads(CONFIG.read_text())["control"]


@pytest.mark.parametrize(
    "extra, words",
    [
        (["--train-positions", "0.6,1.9"], "no data at position 1.9 m"),
        (["--train-positions", "0.6", "--validate-positions", "0.6"], "must not repeat"),
        (["--train-positions", "0.6,abc"], "not a number"),
        (["--train-positions", "3.0"], "outside the screw"),
    ],
)
def test_identify_joints_bad_positions(tmp_path, capsys, extra, words):
    modes = _mode_table(tmp_path)
    rc = main(
        ["identify-joints", "--config", str(CONFIG), "--modes", str(modes), "--generations", "1", *extra]
    )
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: ") and words in err[-1]


def test_identify_joints_frf_with_nan_names_the_row(tmp_path, capsys):
    frf = tmp_path / "frf.csv"
    frf.write_text("position_m,freq_hz,re,im\n0.6,10,1e-7,0\n0.6,11,nan,0\n0.6,12,1e-7,0\n")
    rc = main(["identify-joints", "--config", str(CONFIG), "--frf", str(frf), "--train-positions", "0.6"])
    assert rc == 2
    assert f"error: {frf}: row 3: column re: not a finite number" in capsys.readouterr().err


def test_identify_joints_needs_exactly_one_data_source(capsys):
    assert main(["identify-joints", "--config", str(CONFIG), "--train-positions", "0.6"]) == 2
    assert "exactly one of --frf" in capsys.readouterr().err


def test_identify_joints_from_an_frf_csv(tmp_path):
    from virtualaxis.rcsa.measured import synthetic_frfs, write_frf_csv

    model = rcsa_model_from_config(load_axis_config(CONFIG)).with_joints(TRUTH)
    frf = tmp_path / "frf.csv"
    write_frf_csv(frf, synthetic_frfs(model, [0.6, 1.0, 1.3], np.arange(5.0, 1000.0, 0.25), seed=1))
    out = tmp_path / "ident.json"
    rc = main(
        [
            "identify-joints",
            "--config",
            str(CONFIG),
            "--frf",
            str(frf),
            "--train-positions",
            "0.6,1.0",
            "--validate-positions",
            "1.3",
            "--json",
            str(out),
            "--generations",
            "4",
            "--population",
            "4",
            "--workers",
            "1",
        ]
    )
    assert rc == 0
    doc = json.loads(out.read_text())
    # peaks were picked from the CSV: the measured first mode is the model's 24 Hz mode
    assert abs(doc["train"][0]["measured_frequencies_hz"][0] - 24.0) < 0.5
    # the third mode has a node at 1.3 m: a gap (null), not a number
    assert doc["validate"][0]["measured_frequencies_hz"][2] is None


def test_write_config_refuses_a_file_without_joint_lines(tmp_path):
    from virtualaxis.config import ConfigError
    from virtualaxis.rcsa.config_writer import write_identified_config

    src = tmp_path / "inline.toml"
    src.write_text(
        CONFIG.read_text()
        .replace("nut_stiffness_n_per_m = {", "nut_stiffness_n_per_m= {", 1)
        .replace("[rcsa.joints]", "[rcsa.joints]  # identified here")
    )
    write_identified_config(src, tmp_path / "ok.toml", TRUTH, "test")  # tolerant of spacing and comments
    broken = tmp_path / "broken.toml"
    broken.write_text(
        CONFIG.read_text()
        .replace("[rcsa.joints]\n", "[rcsa.joints]\n# moved\n")
        .replace("\nnut_stiffness_n_per_m =", "\n# nut_stiffness_n_per_m =")
    )
    with pytest.raises(ConfigError, match=r"rcsa\.joints\.nut_stiffness_n_per_m"):
        write_identified_config(broken, tmp_path / "out.toml", TRUTH, "test")
    assert not (tmp_path / "out.toml").exists()
