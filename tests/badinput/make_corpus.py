"""Regenerate the bad-input corpus data files (configs/, traces/, profiles/) from the shipped seed 004 config
and one simulated trace. The files are committed; run this only to rebuild them:

    PYTHONPATH=src python3 tests/badinput/make_corpus.py
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
BASE = (ROOT / "configs" / "seed004-siemens.toml").read_text(encoding="utf-8")


def _cfg(name: str, old: str, new: str) -> None:
    assert old in BASE, old
    (HERE / "configs" / f"{name}.toml").write_text(BASE.replace(old, new, 1), encoding="utf-8")


def _append(name: str, text: str) -> None:
    (HERE / "configs" / f"{name}.toml").write_text(BASE + "\n" + text, encoding="utf-8")


def configs() -> None:
    d = HERE / "configs"
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir()
    mass = "table_mass_kg = { value = 120.0"
    lead = "lead_m = { value = 0.01,"
    _cfg("table_mass_1e-300", mass, "table_mass_kg = { value = 1e-300")
    _cfg("table_mass_nan", mass, "table_mass_kg = { value = nan")
    _cfg("table_mass_negative_zero", mass, "table_mass_kg = { value = -0.0")
    _cfg("table_mass_string", mass, 'table_mass_kg = { value = "120"')
    _cfg("table_mass_bool", mass, "table_mass_kg = { value = true")
    _cfg("table_mass_array", mass, "table_mass_kg = { value = [120.0]")
    _cfg("pole_pairs_1e17", "pole_pairs = { value = 4", "pole_pairs = { value = 1e17")
    _cfg("pole_pairs_fraction", "pole_pairs = { value = 4", "pole_pairs = { value = 4.5")
    _cfg("travel_min_nan", "travel_min_m = { value = -0.4", "travel_min_m = { value = nan")
    _cfg("travel_max_inf", "travel_max_m = { value = 0.4", "travel_max_m = { value = inf")
    _cfg("travel_min_neg_inf", "travel_min_m = { value = -0.4", "travel_min_m = { value = -inf")
    _cfg("travel_min_ge_max", "travel_min_m = { value = -0.4", "travel_min_m = { value = 0.5")
    _cfg("lead_unit_kg", lead, 'lead_m = { value = 10, unit = "kg",')
    _cfg("lead_unit_number", lead, "lead_m = { value = 10, unit = 3,")
    _cfg("lead_unit_mm", lead, 'lead_m = { value = 10, unit = "mm",')  # accepted: 10 mm = 0.01 m
    _cfg("mass_unit_g", mass, 'table_mass_kg = { value = 120000.0, unit = "g"')  # accepted: 120 kg
    _cfg("rated_speed_unit_rpm", "rated_speed_rpm = { value = 3000.0",
         'rated_speed_rpm = { value = 50.0, unit = "rev/s"')
    _cfg("efficiency_unit", "modal_damping_ratio = { value = 0.03", 'modal_damping_ratio = { value = 3, unit = "%"')
    _cfg("lead_extra_field", lead, 'lead_m = { value = 0.01, tolerance = 0.001,')
    _cfg("duplicate_key", "rs_ohm = { value = 1.1", "rs_ohm = 2.0\nrs_ohm = { value = 1.1")
    _cfg("unknown_key", "rs_ohm = { value = 1.1", "rs_ohms = { value = 1.1")
    _cfg("unknown_section", "[backlash]", "[backlsh]")
    _cfg("kv_huge", "kv_per_min = { value = 2725.0", "kv_per_min = { value = 2.725e9")
    _cfg("dc_link_1e308", "dc_link_v = { value = 600.0", "dc_link_v = { value = 1e308")
    _cfg("dc_link_overflow", "dc_link_v = { value = 600.0", "dc_link_v = { value = 1e999")
    _cfg("encoder_counts_huge", "motor_encoder_counts_per_rev = { value = 4194304",
         "motor_encoder_counts_per_rev = { value = 99999999999999999999999")
    _cfg("cycle_not_nested", "speed_cycle_s = { value = 125e-6", "speed_cycle_s = { value = 100e-6")
    _cfg("resonance_above_nyquist", "[limits]",
         "[effects]\nresonance_frequency_hz = 20000.0\nresonance_mass_kg = 10.0\n\n[limits]")
    _append("substeps_1e6", "[simulation]\nmechanical_substeps = 1e6\n")
    _append("substeps_1000", "[simulation]\nmechanical_substeps = 1000\n")
    _append("grid_1e8", "[simulation]\nposition_grid_points = 1e8\n")
    _append("seed_negative", "[simulation]\nseed = -1\n")
    _append("unicode_key", "[simulation]\nsëed = 1\n")
    (d / "empty.toml").write_text("", encoding="utf-8")
    (d / "only_comment.toml").write_text("# nothing here\n", encoding="utf-8")
    (d / "latin1.toml").write_bytes(BASE.replace("40 x 10", "40 \u00d7 10").encode("latin-1"))
    (d / "utf16.toml").write_bytes(BASE.encode("utf-16"))
    (d / "bom.toml").write_bytes(b"\xef\xbb\xbf" + BASE.encode())  # accepted
    (d / "binary.toml").write_bytes(bytes(range(256)) * 8)
    (d / "nul_bytes.toml").write_bytes(BASE.encode()[:200] + b"\x00\x00\x00" + BASE.encode()[200:])
    (d / "truncated.toml").write_text(BASE[: len(BASE) // 2], encoding="utf-8")
    (d / "crlf.toml").write_bytes(BASE.replace("\n", "\r\n").encode())  # accepted


def traces() -> None:
    d = HERE / "traces"
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir()
    good = d / "good.csv"
    subprocess.run([sys.executable, "-m", "virtualaxis.cli.main", "simulate", "--config",
                    str(ROOT / "configs" / "seed004-siemens.toml"), "--profile", "sine:stroke_mm=20,feed_mm_min=3000",
                    "--duration", "0.3", "--out", str(good), "--force"], check=True, capture_output=True)
    lines = good.read_text().splitlines(keepends=True)
    header = lines[0].strip().split(",")
    rows = [ln.strip().split(",") for ln in lines[1:]]

    def write(name: str, hdr: list[str], rws: list[list[str]], tail: str = "\n") -> None:
        text = ",".join(hdr) + "\n" + "\n".join(",".join(r) for r in rws) + tail
        (d / name).write_text(text, encoding="utf-8")

    def col(name: str) -> int:
        return header.index(name)

    def mapped(name: str, column: str, fn) -> None:
        i = col(column)
        write(name, header, [[fn(v) if k == i else v for k, v in enumerate(r)] for r in rows])

    mapped("time_in_ms.csv", "t", lambda v: repr(float(v) * 1000.0))
    mapped("pos_meas_sign_flipped.csv", "pos_meas", lambda v: repr(-float(v)))
    mapped("torque_sign_flipped.csv", "torque_meas", lambda v: repr(-float(v)))
    mapped("pos_meas_in_mm.csv", "pos_meas", lambda v: repr(float(v) * 1000.0))
    mapped("force_ext_1e300.csv", "force_ext", lambda v: "1e300")
    mapped("force_ext_inf.csv", "force_ext", lambda v: "inf")
    write("truncated_last_row.csv", header, rows[:-1] + [rows[-1][:3] + [rows[-1][3][:4]]], tail="")
    write("short_row.csv", header, rows[:100] + [rows[100][:4]] + rows[101:])
    write("duplicate_column.csv", header[:-1] + ["pos_meas"], rows)
    write("missing_t.csv", ["time"] + header[1:], rows)
    write("not_a_number.csv", header, rows[:50] + [[rows[50][0], "abc"] + rows[50][2:]] + rows[51:])
    write("time_backwards.csv", header, rows[:30] + [rows[28]] + rows[31:])
    write("time_gap.csv", header, rows[:200] + rows[260:])
    write("header_only.csv", header, [])
    write("few_rows.csv", header, rows[:5])
    write("nan_run.csv", header, [[*(r[:2]), "nan", *r[3:]] if 100 <= k < 110 else r for k, r in enumerate(rows)])
    (d / "empty.csv").write_text("", encoding="utf-8")
    (d / "binary.csv").write_bytes(bytes(range(256)) * 64)
    text = good.read_text()
    (d / "bom.csv").write_bytes(b"\xef\xbb\xbf" + text.encode())  # accepted
    (d / "latin1_row.csv").write_bytes(text.replace("\n", "\n# \u00b5\n", 1).encode("latin-1"))
    (d / "crlf.csv").write_bytes(text.replace("\n", "\r\n").encode())  # accepted
    (d / "copy_of_good.csv").write_text(text, encoding="utf-8")
    (d / "sidecar_is_folder.csv").write_text(text, encoding="utf-8")
    (d / "sidecar_is_folder.toml").mkdir()
    (d / "sidecar_is_folder.toml" / ".keep").write_text("")
    (d / "sidecar_latin1.csv").write_text(text, encoding="utf-8")
    (d / "sidecar_latin1.toml").write_bytes('notes = "\u00b5m"\n'.encode("latin-1"))
    (d / "sidecar_other_axis.csv").write_text(text, encoding="utf-8")
    (d / "sidecar_other_axis.toml").write_text('axis = "another-axis"\n', encoding="utf-8")


def profiles() -> None:
    d = HERE / "profiles"
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir()
    (d / "good.csv").write_text("t,pos\n0,0\n0.1,0.001\n0.3,0.002\n", encoding="utf-8")
    (d / "bom.csv").write_bytes(b"\xef\xbb\xbft,pos\n0,0\n0.1,0.001\n0.3,0.002\n")  # accepted
    (d / "latin1.csv").write_bytes("t,pos\n0,0\n0.1,0.001 \u00b5m\n".encode("latin-1"))
    (d / "binary.csv").write_bytes(bytes(range(256)) * 4)
    (d / "empty.csv").write_text("", encoding="utf-8")
    (d / "header_only.csv").write_text("t,pos\n", encoding="utf-8")
    (d / "one_row.csv").write_text("t,pos\n0,0\n", encoding="utf-8")
    (d / "no_pos.csv").write_text("t,position\n0,0\n0.1,0.001\n", encoding="utf-8")
    (d / "duplicate_column.csv").write_text("t,pos,pos\n0,0,0\n0.1,0.001,0\n", encoding="utf-8")
    (d / "nan.csv").write_text("t,pos\n0,0\n0.1,nan\n0.2,0.001\n", encoding="utf-8")
    (d / "inf.csv").write_text("t,pos\n0,0\n0.1,inf\n0.2,0.001\n", encoding="utf-8")
    (d / "time_backwards.csv").write_text("t,pos\n0,0\n0.2,0.001\n0.1,0.002\n", encoding="utf-8")
    (d / "short_row.csv").write_text("t,pos\n0,0\n0.1\n0.2,0.001\n", encoding="utf-8")
    (d / "huge_position.csv").write_text("t,pos\n0,0\n0.1,1e300\n", encoding="utf-8")
    (d / "nul.csv").write_bytes(b"t,pos\n0,0\n0.1,0.0\x0001\n")
    (d / "long_field.csv").write_text("t,pos\n0," + "1" * 200_000 + "\n", encoding="utf-8")


if __name__ == "__main__":
    configs()
    traces()
    profiles()
    print(f"corpus written to {HERE}")
