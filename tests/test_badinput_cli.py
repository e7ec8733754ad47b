"""Bad-input corpus: every case runs through the real CLI (``main([...])`` in-process) and must either
exit 2 with ONE ``error:`` line naming what is wrong (file / row / column / key / option, and what was expected)
or succeed with a checked result. Never a traceback, an ``internal error``, a hang (each case has a timeout) or
a silently wrong result. The data files live in ``tests/badinput/`` (``make_corpus.py`` rebuilds them);
``docs/bad-input.md`` lists the classes.
"""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

import pytest

from virtualaxis.cli.main import main

ROOT = Path(__file__).resolve().parents[1]
D = ROOT / "tests" / "badinput"
C4 = ROOT / "configs" / "seed004-siemens.toml"
RIGID = ROOT / "configs" / "examples" / "rigid-force-axis.toml"
RCSA = ROOT / "configs" / "seed002-usst.toml"
STEP = "step:distance_um=10"


def _cfg(name: str) -> str:
    return str(D / "configs" / f"{name}.toml")


def _tr(name: str) -> str:
    return str(D / "traces" / name)


def _pr(name: str) -> str:
    return f"file:{D / 'profiles' / name}"


# (id, argv; "{T}" is the case's tmp folder, expected substrings of the one error line)
# every config case runs through `modal` (fast: loads the config, one modal analysis)
CONFIG_ERRORS = [
    ("cfg-mass-1e-300", "table_mass_1e-300", ["mechanics.table_mass_kg", "plausible range"]),
    ("cfg-mass-nan", "table_mass_nan", ["mechanics.table_mass_kg", "finite"]),
    ("cfg-mass-negative-zero", "table_mass_negative_zero", ["mechanics.table_mass_kg", "> 0"]),
    ("cfg-mass-string", "table_mass_string", ["mechanics.table_mass_kg", "must be a number"]),
    ("cfg-mass-bool", "table_mass_bool", ["mechanics.table_mass_kg", "must be a number"]),
    ("cfg-mass-array", "table_mass_array", ["mechanics.table_mass_kg", "must be a number"]),
    ("cfg-pole-pairs-1e17", "pole_pairs_1e17", ["motor.pole_pairs", "plausible range 1 .. 128"]),
    ("cfg-pole-pairs-fraction", "pole_pairs_fraction", ["motor.pole_pairs", "integer"]),
    ("cfg-travel-min-nan", "travel_min_nan", ["limits.travel_min_m", "finite"]),
    ("cfg-travel-max-inf", "travel_max_inf", ["limits.travel_max_m", "finite"]),
    ("cfg-travel-min-neg-inf", "travel_min_neg_inf", ["limits.travel_min_m", "finite"]),
    ("cfg-travel-min-ge-max", "travel_min_ge_max", ["limits.travel_max_m", "greater than limits.travel_min_m"]),
    ("cfg-unit-of-other-quantity", "lead_unit_kg", ["mechanics.lead_m", "unit 'kg'", "'mm'"]),
    ("cfg-unit-not-a-string", "lead_unit_number", ["mechanics.lead_m", "unit must be a string"]),
    ("cfg-unit-on-ratio", "efficiency_unit", ["mechanics.modal_damping_ratio", "unit '%'"]),
    ("cfg-extra-field", "lead_extra_field", ["mechanics.lead_m", "tolerance"]),
    ("cfg-duplicate-key", "duplicate_key", ["duplicate_key.toml", "not valid TOML", "line"]),
    ("cfg-unknown-key", "unknown_key", ["motor.rs_ohms", "unknown key", "rs_ohm"]),
    ("cfg-unknown-section", "unknown_section", ["backlsh", "unknown section"]),
    ("cfg-kv-huge", "kv_huge", ["control.kv_per_min", "plausible range"]),
    ("cfg-dc-link-1e308", "dc_link_1e308", ["inverter.dc_link_v", "plausible range"]),
    ("cfg-dc-link-overflow", "dc_link_overflow", ["inverter.dc_link_v", "finite"]),
    ("cfg-encoder-counts-huge", "encoder_counts_huge", ["sensors.motor_encoder_counts_per_rev", "plausible"]),
    ("cfg-cycles-not-nested", "cycle_not_nested", ["control.speed_cycle_s", "integer multiple"]),
    ("cfg-resonance-above-nyquist", "resonance_above_nyquist", ["effects.resonance_frequency_hz", "Nyquist"]),
    ("cfg-substeps-1e6", "substeps_1e6", ["simulation.mechanical_substeps", "plausible range"]),
    ("cfg-substeps-1000", "substeps_1000", ["simulation.mechanical_substeps", "mechanical steps per simulated"]),
    ("cfg-grid-1e8", "grid_1e8", ["simulation.position_grid_points", "plausible range 1 .. 2001"]),
    ("cfg-seed-negative", "seed_negative", ["simulation.seed", "plausible range 0"]),
    ("cfg-unicode-key", "unicode_key", ["not valid TOML", "line 89"]),
    ("cfg-empty", "empty", ["empty.toml", "axis", "missing section"]),
    ("cfg-only-comment", "only_comment", ["only_comment.toml", "missing section"]),
    ("cfg-latin1", "latin1", ["latin1.toml", "line 13", "not UTF-8"]),
    ("cfg-utf16", "utf16", ["utf16.toml", "line 1", "not UTF-8"]),
    ("cfg-binary", "binary", ["binary.toml", "not UTF-8"]),
    ("cfg-nul-bytes", "nul_bytes", ["nul_bytes.toml", "not valid TOML"]),
    ("cfg-truncated", "truncated", ["truncated.toml"]),
]

CASES: list[tuple[str, list[str], list[str]]] = [
    (cid, ["modal", "--config", _cfg(name)], [f"{name}.toml", *want]) for cid, name, want in CONFIG_ERRORS
]
CASES += [
    # ---- config paths
    ("cfg-missing-file", ["modal", "--config", "{T}/nope.toml"], ["nope.toml", "not found"]),
    ("cfg-is-folder", ["modal", "--config", "{T}"], ["is a folder"]),
    ("cfg-dev-zero", ["modal", "--config", "/dev/zero"], ["/dev/zero", "larger than 4 MiB"]),
    ("cfg-is-a-trace", ["modal", "--config", _tr("good.csv")], ["good.csv", "not valid TOML"]),
    ("cfg-fifo", ["modal", "--config", "{T}/fifo.csv"], ["fifo.csv", "not a regular file"]),
    ("cfg-unreadable-proc", ["modal", "--config", "/proc/self/mem"], ["/proc/self/mem", "cannot read"]),
    # ---- simulate: durations, seeds, profiles
    ("sim-duration-1e7", ["simulate", "--config", str(C4), "--profile", STEP, "--duration", "1e7", "--out",
                          "{T}/t.csv"], ["--duration", "MiB", "--max-output-mb"]),
    ("sim-duration-inf", ["simulate", "--config", str(C4), "--profile", STEP, "--duration", "inf", "--out",
                          "{T}/t.csv"], ["--duration", "finite", "inf"]),
    ("sim-duration-nan", ["simulate", "--config", str(C4), "--profile", STEP, "--duration", "nan", "--out",
                          "{T}/t.csv"], ["--duration", "finite"]),
    ("sim-duration-negative", ["simulate", "--config", str(C4), "--profile", STEP, "--duration", "-1", "--out",
                               "{T}/t.csv"], ["--duration", "> 0"]),
    ("sim-duration-zero", ["simulate", "--config", str(C4), "--profile", STEP, "--duration", "0", "--out",
                           "{T}/t.csv"], ["--duration", "> 0"]),
    ("sim-step-at-1e9", ["simulate", "--config", str(C4), "--profile", "step:distance_um=10,at_s=1e9", "--out",
                         "{T}/t.csv"], ["at_s=1e9", "MiB"]),
    ("sim-step-at-1e9-short-run", ["simulate", "--config", str(C4), "--profile", "step:distance_um=10,at_s=1e9",
                                   "--duration", "0.1", "--out", "{T}/t.csv"], ["step at 1e+09 s", "after the end"]),
    ("sim-step-at-negative", ["simulate", "--config", str(C4), "--profile", "step:distance_um=10,at_s=-1", "--out",
                              "{T}/t.csv"], ["at_s", ">= 0"]),
    ("sim-seed-negative", ["simulate", "--config", str(C4), "--profile", STEP, "--seed", "-1", "--out",
                           "{T}/t.csv"], ["--seed", "0 .. 2^63-1"]),
    ("sim-seed-huge", ["simulate", "--config", str(C4), "--profile", STEP, "--seed", str(2**70), "--out",
                       "{T}/t.csv"], ["--seed"]),
    ("sim-max-output-nan", ["simulate", "--config", str(C4), "--profile", STEP, "--max-output-mb", "nan", "--out",
                            "{T}/t.csv"], ["--max-output-mb"]),
    ("prof-duplicate-key", ["simulate", "--config", str(C4), "--profile", "step:distance_um=10,distance_um=20",
                            "--out", "{T}/t.csv"], ["distance_um", "given twice"]),
    ("prof-unknown-kind", ["simulate", "--config", str(C4), "--profile", "square:a=1", "--out", "{T}/t.csv"],
     ["unknown kind 'square'"]),
    ("prof-no-colon", ["simulate", "--config", str(C4), "--profile", "sine", "--out", "{T}/t.csv"],
     ["expected KIND:params"]),
    ("prof-nan-param", ["simulate", "--config", str(C4), "--profile", "sine:stroke_mm=nan,feed_mm_min=100", "--out",
                        "{T}/t.csv"], ["stroke_mm", "finite"]),
    ("prof-beyond-velocity", ["simulate", "--config", str(C4), "--profile", "sine:stroke_mm=100,feed_mm_min=1e6",
                              "--out", "{T}/t.csv"], ["max_velocity_m_s"]),
    ("prof-beyond-travel", ["simulate", "--config", str(C4), "--profile", "sine:stroke_mm=5000,feed_mm_min=100",
                            "--out", "{T}/t.csv"], ["software limits"]),
    ("prof-negative-dwell", ["simulate", "--config", str(C4), "--profile",
                             "ptp:distance_mm=5,feed_mm_min=1000,accel_m_s2=1,jerk_m_s3=50,dwell_s=-5", "--out",
                             "{T}/t.csv"], ["dwell_s", ">= 0"]),
    ("prof-chirp-above-nyquist", ["simulate", "--config", str(C4), "--profile",
                                  "chirp:amplitude_um=0.001,f0_hz=1,f1_hz=5000", "--duration", "0.1", "--out",
                                  "{T}/t.csv"], ["5000 Hz", "Nyquist"]),
    ("prof-file-missing", ["simulate", "--config", str(C4), "--profile", "file:{T}/none.csv", "--out", "{T}/t.csv"],
     ["none.csv", "not found"]),
    ("prof-file-empty-name", ["simulate", "--config", str(C4), "--profile", "file:", "--out", "{T}/t.csv"],
     ["file: needs a file name"]),
    ("prof-file-folder", ["simulate", "--config", str(C4), "--profile", "file:{T}", "--out", "{T}/t.csv"],
     ["is a folder"]),
    ("prof-file-latin1", ["simulate", "--config", str(C4), "--profile", _pr("latin1.csv"), "--out", "{T}/t.csv"],
     ["latin1.csv", "row 3", "not UTF-8"]),
    ("prof-file-binary", ["simulate", "--config", str(C4), "--profile", _pr("binary.csv"), "--out", "{T}/t.csv"],
     ["binary.csv", "row"]),
    ("prof-file-empty", ["simulate", "--config", str(C4), "--profile", _pr("empty.csv"), "--out", "{T}/t.csv"],
     ["empty.csv", "row 1", "empty file"]),
    ("prof-file-header-only", ["simulate", "--config", str(C4), "--profile", _pr("header_only.csv"), "--out",
                               "{T}/t.csv"], ["header_only.csv", "two samples"]),
    ("prof-file-one-row", ["simulate", "--config", str(C4), "--profile", _pr("one_row.csv"), "--out", "{T}/t.csv"],
     ["one_row.csv", "two samples"]),
    ("prof-file-no-pos", ["simulate", "--config", str(C4), "--profile", _pr("no_pos.csv"), "--out", "{T}/t.csv"],
     ["no_pos.csv", "row 1", "'pos'"]),
    ("prof-file-duplicate-column", ["simulate", "--config", str(C4), "--profile", _pr("duplicate_column.csv"),
                                    "--out", "{T}/t.csv"], ["duplicate_column.csv", "row 1", "column pos",
                                                            "duplicate"]),
    ("prof-file-nan", ["simulate", "--config", str(C4), "--profile", _pr("nan.csv"), "--out", "{T}/t.csv"],
     ["nan.csv", "row 3", "column pos", "finite"]),
    ("prof-file-inf", ["simulate", "--config", str(C4), "--profile", _pr("inf.csv"), "--out", "{T}/t.csv"],
     ["inf.csv", "row 3", "column pos", "finite"]),
    ("prof-file-time-backwards", ["simulate", "--config", str(C4), "--profile", _pr("time_backwards.csv"), "--out",
                                  "{T}/t.csv"], ["time_backwards.csv", "row 4", "column t", "increase"]),
    ("prof-file-short-row", ["simulate", "--config", str(C4), "--profile", _pr("short_row.csv"), "--out",
                             "{T}/t.csv"], ["short_row.csv", "row 3", "column pos"]),
    ("prof-file-huge-position", ["simulate", "--config", str(C4), "--profile", _pr("huge_position.csv"), "--out",
                                 "{T}/t.csv"], ["huge_position.csv", "max_velocity_m_s"]),
    ("prof-file-nul", ["simulate", "--config", str(C4), "--profile", _pr("nul.csv"), "--out", "{T}/t.csv"],
     ["nul.csv", "row 3"]),
    ("prof-file-long-field", ["simulate", "--config", str(C4), "--profile", _pr("long_field.csv"), "--out",
                              "{T}/t.csv"], ["long_field.csv", "row 2"]),
    # ---- output paths (checked before any work)
    ("out-is-folder", ["simulate", "--config", str(C4), "--profile", STEP, "--out", "{T}"], ["--out", "is a folder"]),
    ("out-under-proc", ["simulate", "--config", str(C4), "--profile", STEP, "--out", "/proc/trace.csv"],
     ["--out", "/proc/trace.csv", "virtual file system"]),
    ("out-parent-is-file", ["simulate", "--config", str(C4), "--profile", STEP, "--out", "{T}/f.csv/t.csv"],
     ["--out", "f.csv is a file"]),
    ("out-exists", ["simulate", "--config", str(C4), "--profile", STEP, "--out", "{T}/f.csv"],
     ["--out", "f.csv exists", "--force"]),
    ("out-is-profile-input", ["simulate", "--config", str(C4), "--profile", "file:{T}/moves.csv", "--out",
                              "{T}/moves.csv", "--force"], ["moves.csv is also an input"]),
    ("out-is-config", ["simulate", "--config", "{T}/cfg.toml", "--profile", STEP, "--out", "{T}/cfg.toml", "--force"],
     ["cfg.toml is also an input"]),
    ("out-symlink-to-config", ["simulate", "--config", "{T}/cfg.toml", "--profile", STEP, "--out", "{T}/link.csv",
                               "--force"], ["link.csv is also an input"]),
    ("out-dangling-symlink", ["simulate", "--config", str(C4), "--profile", STEP, "--out", "{T}/dangling.csv"],
     ["dangling"]),
    ("out-json-is-folder", ["simulate", "--config", str(C4), "--profile", STEP, "--out", "{T}/t.csv", "--json",
                            "{T}"], ["--json", "is a folder"]),
    ("out-json-same-as-out", ["simulate", "--config", str(C4), "--profile", STEP, "--out", "{T}/t.csv", "--json",
                              "{T}/t.csv"], ["--json", "also the trace output"]),
    ("out-empty", ["simulate", "--config", str(C4), "--profile", STEP, "--out", ""], ["--out", "empty path"]),
    ("modal-json-under-proc", ["modal", "--config", str(C4), "--json", "/proc/self/x.json"],
     ["--json", "virtual file system"]),
    ("modal-plot-is-file", ["modal", "--config", str(C4), "--plot", "{T}/f.csv"], ["--plot", "is a file"]),
    ("modal-positions-nan", ["modal", "--config", str(C4), "--positions", "nan"], ["--positions", "finite"]),
    ("modal-positions-outside", ["modal", "--config", str(C4), "--positions", "1.5"], ["--positions", "0..1"]),
    # ---- frf
    ("frf-points-0", ["frf", "--config", str(C4), "--points", "0", "--out", "{T}/o"], ["--points", "2 .. "]),
    ("frf-points-1e9", ["frf", "--config", str(C4), "--points", "1000000000", "--out", "{T}/o"], ["--points"]),
    ("frf-fmax-inf", ["frf", "--config", str(C4), "--fmax", "inf", "--out", "{T}/o"], ["--fmax", "finite"]),
    ("frf-fmax-nan", ["frf", "--config", str(C4), "--fmax", "nan", "--out", "{T}/o"], ["--fmax"]),
    ("frf-fmin-negative", ["frf", "--config", str(C4), "--fmin", "-1", "--out", "{T}/o"], ["--fmin"]),
    ("frf-fmax-above-nyquist", ["frf", "--config", str(C4), "--fmax", "1e6", "--out", "{T}/o"], ["--fmax", "Nyquist"]),
    ("frf-position-nan", ["frf", "--config", str(C4), "--position", "nan", "--out", "{T}/o"], ["--position"]),
    ("frf-out-is-file", ["frf", "--config", str(C4), "--out", "{T}/f.csv"], ["--out", "is a file"]),
    ("frf-out-exists", ["frf", "--config", str(C4), "--out", "{T}/done"], ["frf.csv", "--force"]),
    # reports of serve / conformance and the bench folder: never replaced without --force (checked before the
    # bus is opened or any case runs)
    ("serve-json-exists", ["serve", "--can", "udp_multicast:239.74.1.1", "--json", "{T}/done/report.json"],
     ["--json", "report.json: exists", "--force"]),
    ("conformance-json-exists", ["conformance", "--can", "udp_multicast:239.74.1.1", "--json",
                                 "{T}/done/report.json"], ["--json", "report.json exists", "--force"]),
    ("conformance-junit-exists", ["conformance", "--can", "udp_multicast:239.74.1.1", "--junit",
                                  "{T}/done/frf.csv"], ["--junit", "frf.csv exists", "--force"]),
    ("gap-bench-out-holds-files", ["gap-bench", "--out", "{T}/done", "--quick", "--cases", "rigid-clean"],
     ["--out", "holds files", "--force"]),
    # ---- study / rcsa / identify-joints
    ("study-values-negative", ["study", "kv-sweep", "--config", str(C4), "--out", "{T}/s", "--values", "-5"],
     ["--values", "> 0"]),
    ("study-values-inf", ["study", "feed-sweep", "--config", str(C4), "--out", "{T}/s", "--values", "inf"],
     ["--values", "finite"]),
    ("study-out-under-proc", ["study", "support-stiffness", "--config", str(C4), "--out", "/proc/s"],
     ["--out", "virtual file system"]),
    ("rcsa-positions-nan", ["rcsa", "--config", str(RCSA), "--positions", "nan"], ["--positions"]),
    ("rcsa-json-folder", ["rcsa", "--config", str(RCSA), "--json", "{T}"], ["--json", "is a folder"]),
    ("ident-generations-0", ["identify-joints", "--config", str(RCSA), "--modes", "{T}/m.csv", "--train-positions",
                             "0.6", "--generations", "0"], ["--generations", "1 .. "]),
    ("ident-write-config-is-input", ["identify-joints", "--config", "{T}/cfg2.toml", "--modes", "{T}/m.csv",
                                     "--train-positions", "0.6", "--write-config", "{T}/cfg2.toml", "--force"],
     ["--write-config", "also an input"]),
    ("ident-frf-is-folder", ["identify-joints", "--config", str(RCSA), "--frf", "{T}", "--train-positions", "0.6"],
     ["--frf", "is a folder"]),
    ("ident-modes-latin1", ["identify-joints", "--config", str(RCSA), "--modes", "{T}/m_latin1.csv",
                            "--train-positions", "0.6"], ["m_latin1.csv", "UTF-8"]),
    ("ident-modes-nan", ["identify-joints", "--config", str(RCSA), "--modes", "{T}/m_nan.csv",
                         "--train-positions", "0.6"], ["m_nan.csv", "row 2", "column freq_hz", "finite"]),
    ("ident-json-under-proc", ["identify-joints", "--config", str(RCSA), "--modes", "{T}/m.csv",
                               "--train-positions", "0.6", "--json", "/proc/x.json"], ["--json", "virtual file"]),
    ("gap-bench-seed-negative", ["gap-bench", "--out", "{T}/gb", "--seed", "-1", "--cases", "rigid-clean"],
     ["--seed must be >= 0"]),
    ("demo-stroke-nan", ["demo", "--out", "{T}/demo", "--stroke-mm", "nan", "--no-pace"], ["--stroke-mm"]),
    ("demo-out-is-file", ["demo", "--out", "{T}/f.csv", "--no-pace"], ["f.csv", "cannot create output directory"]),
    ("demo-config-latin1", ["demo", "--config", _cfg("latin1"), "--out", "{T}/demo", "--no-pace"],
     ["latin1.toml", "line 13", "not UTF-8"]),
    # ---- diagnose: traces
    ("diag-trace-time-in-ms", ["diagnose", "--config", str(C4), _tr("time_in_ms.csv"), "--out", "{T}/d"],
     ["time_in_ms.csv", "column t", "sample interval 1 s", "milliseconds"]),
    ("diag-trace-sign-flipped", ["diagnose", "--config", str(C4), _tr("pos_meas_sign_flipped.csv"), "--out",
                                 "{T}/d"], ["pos_meas_sign_flipped.csv", "column pos_meas"]),
    ("diag-torque-sign-flipped", ["diagnose", "--config", str(C4), _tr("torque_sign_flipped.csv"), "--out",
                                  "{T}/d"], ["torque_sign_flipped.csv", "column torque_meas", "sign-flipped"]),
    ("diag-trace-pos-in-mm", ["diagnose", "--config", str(C4), _tr("pos_meas_in_mm.csv"), "--out", "{T}/d"],
     ["pos_meas_in_mm.csv", "column pos_meas"]),
    ("diag-force-ext-1e300", ["diagnose", "--config", str(C4), _tr("force_ext_1e300.csv"), "--out", "{T}/d"],
     ["force_ext_1e300.csv", "row 2", "column force_ext", "peak drive force"]),
    ("diag-force-ext-inf", ["diagnose", "--config", str(C4), _tr("force_ext_inf.csv"), "--out", "{T}/d"],
     ["force_ext_inf.csv", "column force_ext"]),
    ("diag-fit-equals-holdout", ["diagnose", "--config", str(C4), _tr("good.csv"), "--holdout", _tr("good.csv"),
                                 "--out", "{T}/d"], ["good.csv", "same content", "fit and held-out"]),
    ("diag-holdout-is-a-copy", ["diagnose", "--config", str(C4), _tr("good.csv"), "--holdout",
                                _tr("copy_of_good.csv"), "--out", "{T}/d"], ["copy_of_good.csv", "same content"]),
    ("diag-short-row", ["diagnose", "--config", str(C4), _tr("short_row.csv"), "--out", "{T}/d"],
     ["short_row.csv", "row 102", "fields"]),
    ("diag-duplicate-column", ["diagnose", "--config", str(C4), _tr("duplicate_column.csv"), "--out", "{T}/d"],
     ["duplicate_column.csv", "row 1", "column pos_meas", "duplicate"]),
    ("diag-missing-t", ["diagnose", "--config", str(C4), _tr("missing_t.csv"), "--out", "{T}/d"],
     ["missing_t.csv", "column t", "missing"]),
    ("diag-not-a-number", ["diagnose", "--config", str(C4), _tr("not_a_number.csv"), "--out", "{T}/d"],
     ["not_a_number.csv", "row 52", "column pos_cmd", "not a number"]),
    ("diag-time-backwards", ["diagnose", "--config", str(C4), _tr("time_backwards.csv"), "--out", "{T}/d"],
     ["time_backwards.csv", "column t", "not increasing"]),
    ("diag-time-gap", ["diagnose", "--config", str(C4), _tr("time_gap.csv"), "--out", "{T}/d"],
     ["time_gap.csv", "column t", "gap"]),
    ("diag-header-only", ["diagnose", "--config", str(C4), _tr("header_only.csv"), "--out", "{T}/d"],
     ["header_only.csv", "no data rows"]),
    ("diag-few-rows", ["diagnose", "--config", str(C4), _tr("few_rows.csv"), "--out", "{T}/d"],
     ["few_rows.csv", "at least 16"]),
    ("diag-empty", ["diagnose", "--config", str(C4), _tr("empty.csv"), "--out", "{T}/d"],
     ["empty.csv", "row 1", "empty file"]),
    ("diag-binary", ["diagnose", "--config", str(C4), _tr("binary.csv"), "--out", "{T}/d"], ["binary.csv"]),
    ("diag-latin1-row", ["diagnose", "--config", str(C4), _tr("latin1_row.csv"), "--out", "{T}/d"],
     ["latin1_row.csv", "not UTF-8"]),
    ("diag-trace-dev-zero", ["diagnose", "--config", str(C4), "/dev/zero", "--out", "{T}/d"],
     ["/dev/zero", "not a regular file"]),
    ("diag-trace-fifo", ["diagnose", "--config", str(C4), "{T}/fifo.csv", "--out", "{T}/d"],
     ["fifo.csv", "not a regular file"]),
    ("diag-trace-header-1mb", ["diagnose", "--config", str(C4), "{T}/wide.csv", "--out", "{T}/d"],
     ["wide.csv", "row 1", "header row longer"]),
    ("prof-file-dev-zero", ["simulate", "--config", str(C4), "--profile", "file:/dev/zero", "--out", "{T}/t.csv"],
     ["/dev/zero", "not a regular file"]),
    ("diag-sidecar-fifo", ["diagnose", "--config", str(C4), "{T}/sc.csv", "--out", "{T}/d"],
     ["sc.toml", "not a regular file"]),
    ("diag-trace-missing", ["diagnose", "--config", str(C4), "{T}/none.csv", "--out", "{T}/d"],
     ["none.csv", "not found"]),
    ("diag-trace-folder", ["diagnose", "--config", str(C4), "{T}", "--out", "{T}/d"], ["is a folder"]),
    ("diag-sidecar-folder", ["diagnose", "--config", str(C4), _tr("sidecar_is_folder.csv"), "--out", "{T}/d"],
     ["sidecar_is_folder.toml", "is a folder"]),
    ("diag-sidecar-latin1", ["diagnose", "--config", str(C4), _tr("sidecar_latin1.csv"), "--out", "{T}/d"],
     ["sidecar_latin1.toml", "not UTF-8"]),
    ("diag-sidecar-other-axis", ["diagnose", "--config", str(C4), _tr("sidecar_other_axis.csv"), "--out", "{T}/d"],
     ["sidecar_other_axis.toml", "another-axis"]),
    ("diag-out-is-a-trace", ["diagnose", "--config", str(C4), _tr("good.csv"), "--out", _tr("good.csv")],
     ["--out", "is a file"]),
    ("diag-out-under-proc", ["diagnose", "--config", str(C4), _tr("good.csv"), "--out", "/proc/diag"],
     ["--out", "virtual file system"]),
    ("diag-out-exists", ["diagnose", "--config", str(C4), _tr("good.csv"), "--out", "{T}/done"],
     ["report.json", "--force"]),
    ("diag-jobs-0", ["diagnose", "--config", str(C4), _tr("good.csv"), "--out", "{T}/d", "--jobs", "0"], ["--jobs"]),
]

# ---- one representative case per defect class of docs/bad-input.md
CASES += [
    # option errors argparse reports: one line, not a usage block
    ("opt-not-an-int", ["frf", "--config", str(C4), "--points", "1.5", "--out", "{T}/o"],
     ["error: virtualaxis frf: argument --points", "invalid int value: '1.5'"]),
    ("opt-empty-float", ["simulate", "--config", str(C4), "--profile", STEP, "--duration", "", "--out", "{T}/t.csv"],
     ["argument --duration", "invalid float value"]),
    # subnormal numbers (1e-320): a typing error, never a value
    ("cfg-subnormal", ["modal", "--config", "{T}/subnormal.toml"], ["mechanics.lead_m", "subnormal"]),
    ("prof-subnormal", ["simulate", "--config", str(C4), "--profile", "sine:stroke_mm=1e-320,feed_mm_min=100",
                        "--out", "{T}/t.csv"], ["stroke_mm", "subnormal"]),
    ("frf-fmin-subnormal", ["frf", "--config", str(C4), "--fmin", "1e-320", "--out", "{T}/o"], ["--fmin", "below"]),
    ("sim-duration-below-one-cycle", ["simulate", "--config", str(C4), "--profile", STEP, "--duration", "1e-320",
                                      "--out", "{T}/t.csv"], ["--duration", "shorter than one position cycle"]),
    # numbers beyond the 64-bit range and non-finite values in sections other packages own
    ("cfg-int-400-digits", ["modal", "--config", "{T}/bigint.toml"], ["effects.force_offset_n", "400 digits"]),
    ("cfg-extension-nan", ["modal", "--config", "{T}/extnan.toml"], ["metadata.weight", "finite"]),
    ("cfg-empty-name", ["modal", "--config", "{T}/noname.toml"], ["axis.name", "must not be empty"]),
    # huge values that overflowed an int (traceback before)
    ("sim-duration-1e308", ["simulate", "--config", str(C4), "--profile", STEP, "--duration", "1e308", "--out",
                            "{T}/t.csv"], ["--duration", "MiB"]),
    # empty or repeated list options silently meant "the default" or gave NaN results
    ("modal-positions-empty", ["modal", "--config", str(C4), "--positions", ""], ["--positions", "empty list"]),
    ("modal-positions-twice", ["modal", "--config", str(C4), "--positions", "0.5,0.5"], ["--positions", "twice"]),
    ("study-values-empty", ["study", "kv-sweep", "--config", str(C4), "--out", "{T}/s", "--values", ""],
     ["--values", "empty list"]),
    ("study-values-twice", ["study", "kv-sweep", "--config", str(C4), "--out", "{T}/s", "--values", "5,5"],
     ["--values", "twice"]),
    ("study-values-out-of-range", ["study", "feed-sweep", "--config", str(C4), "--out", "{T}/s", "--values",
                                   "1e308"], ["--values", "1e+308 is outside"]),
    ("diag-effects-empty", ["diagnose", "--config", str(C4), _tr("good.csv"), "--out", "{T}/d", "--effects", ""],
     ["--effects", "empty effect name"]),
    ("gap-bench-cases-empty", ["gap-bench", "--out", "{T}/gb", "--cases", ""], ["--cases", "empty case name"]),
    ("gap-bench-cases-unknown", ["gap-bench", "--out", "{T}/gb", "--cases", "bogus"], ["--cases", "unknown", "--list"]),
    ("diag-scheduler-garbage", ["diagnose", "--config", str(C4), _tr("good.csv"), "--out", "{T}/d", "--scheduler",
                                "nonsense"], ["--scheduler", "tcp://HOST:PORT"]),
    # an option checked only after the inputs were read (notes printed before the error)
    ("ident-weight-nan-first", ["identify-joints", "--config", str(RCSA), "--modes", "{T}/m.csv",
                                "--train-positions", "0.6", "--amplitude-weight", "nan"], ["--amplitude-weight"]),
    # output paths: a refused command leaves no folder; names too long, loops, one path for two outputs, '~', '/'
    ("out-folder-not-left-behind", ["frf", "--config", str(C4), "--points", "0", "--out", "{T}/new/o"],
     ["--points"]),
    ("out-name-too-long", ["simulate", "--config", str(C4), "--profile", STEP, "--out", "{T}/" + "a" * 300 + ".csv"],
     ["--out", "255 bytes"]),
    ("out-name-too-long-for-temp", ["simulate", "--config", str(C4), "--profile", STEP, "--out",
                                    "{T}/" + "a" * 240 + ".csv"], ["--out", "temporary name"]),
    ("out-symlink-loop", ["simulate", "--config", str(C4), "--profile", STEP, "--out", "{T}/loop"],
     ["--out", "loop"]),
    ("out-same-for-json-and-plot", ["modal", "--config", str(C4), "--json", "{T}/x", "--plot", "{T}/x"],
     ["--plot", "also the output of --json"]),
    ("out-tilde-not-expanded", ["simulate", "--config", str(C4), "--profile", STEP, "--out", "~/t.csv"],
     ["--out", "'~'"]),
    ("out-suffix-not-written", ["simulate", "--config", str(C4), "--profile", STEP, "--out", "{T}/t.xlsx"],
     ["--out", "not as '.xlsx'"]),
    ("out-trailing-slash", ["simulate", "--config", str(C4), "--profile", STEP, "--out", "{T}/t.csv/"],
     ["--out", "ends with '/'"]),
    # traces and sidecars: no motion (a traceback in the plots before), sidecar fields of the wrong type
    ("diag-trace-no-motion", ["diagnose", "--config", str(C4), "{T}/still.csv", "--out", "{T}/d"],
     ["still.csv", "column pos_cmd", "does not move"]),
    ("diag-trace-epoch-time", ["diagnose", "--config", str(C4), "{T}/epoch.csv", "--out", "{T}/d"],
     ["epoch.csv", "column t", "subtract the start time"]),
    # rows are the file's lines: blank lines before the bad one are counted, a row of empty fields is missing
    ("diag-trace-blank-then-unsorted", ["diagnose", "--config", str(C4), "{T}/blank_unsorted.csv", "--out", "{T}/d"],
     ["blank_unsorted.csv", "row 13", "column t", "time is not increasing"]),
    ("diag-trace-blank-then-gap", ["diagnose", "--config", str(C4), "{T}/blank_gap.csv", "--out", "{T}/d"],
     ["blank_gap.csv", "row 12", "column t", "between rows 11 and 12"]),
    ("diag-trace-empty-fields-row", ["diagnose", "--config", str(C4), "{T}/commas.csv", "--out", "{T}/d"],
     ["commas.csv", "row 9", "column t", "missing value"]),
    ("diag-trace-semicolons", ["diagnose", "--config", str(C4), "{T}/semi.csv", "--out", "{T}/d"],
     ["semi.csv", "row 1", "separated by semicolons", "comma-separated"]),
    ("diag-trace-units-in-header", ["diagnose", "--config", str(C4), "{T}/units.csv", "--out", "{T}/d"],
     ["units.csv", "row 1", "without units", "'t [SI]'"]),
    ("diag-trace-unit-suffixes", ["diagnose", "--config", str(C4), "{T}/suffixes.csv", "--out", "{T}/d"],
     ["suffixes.csv", "row 1", "no known column", "without units", "'t_s'"]),
    ("diag-trace-position-in-mm-named", ["diagnose", "--config", str(C4), "{T}/pos_mm.csv", "--out", "{T}/d"],
     ["pos_mm.csv", "column pos_meas_mm", "'pos_meas' is", "without units"]),
    ("diag-trace-upper-case", ["diagnose", "--config", str(C4), "{T}/upper.csv", "--out", "{T}/d"],
     ["upper.csv", "column t", "'T' is not it", "lower case"]),
    ("diag-trace-inf", ["diagnose", "--config", str(C4), "{T}/inf.csv", "--out", "{T}/d"],
     ["inf.csv", "row 5", "column pos_meas", "inf is not a finite number"]),
    ("diag-sidecar-axis-wrong-type", ["diagnose", "--config", str(C4), "{T}/sc2.csv", "--out", "{T}/d"],
     ["sc2.toml", "key axis", "axis name"]),
    # serve / conformance / fault: refused before the bus opens (forever, hangs, tracebacks at the end before)
    ("serve-duration-inf", ["serve", "--config", str(C4), "--can", "virtual:a18", "--duration", "inf"],
     ["--duration", "finite"]),
    ("serve-status-interval-negative", ["serve", "--config", str(C4), "--can", "virtual:a18", "--duration", "1",
                                        "--status-interval", "-1"], ["--status-interval"]),
    ("serve-latency-probe-folder", ["serve", "--config", str(C4), "--can", "virtual:a18", "--duration", "1",
                                    "--latency-probe", "{T}"], ["--latency-probe", "is a folder"]),
    ("serve-axis-names-twice", ["serve", "--can", "virtual:a18", "--duration", "1", "--axis", f"X=1:{C4}", "--axis",
                                f"X=2:{C4}"], ["--axis", "names must be unique"]),
    ("serve-eds-not-an-eds", ["serve", "--config", str(C4), "--can", "virtual:a18", "--duration", "1", "--eds",
                              str(C4)], ["seed004-siemens.toml", "not an EDS file"]),
    ("serve-udp-not-multicast", ["serve", "--config", str(C4), "--can", "udp_multicast:1.2.3.4", "--duration", "1",
                                 "--bitrate", "0"], ["1.2.3.4 is not a multicast address"]),
    ("conformance-sdo-timeout-nan", ["conformance", "--can", "virtual:nobody", "--sdo-timeout", "nan"],
     ["--sdo-timeout"]),
    ("fault-timeout-negative", ["fault", "--can", "virtual:nobody", "--timeout", "-1", "status"], ["--timeout"]),
]


def _setup(tmp: Path) -> None:
    (tmp / "f.csv").write_text("x\n")
    (tmp / "moves.csv").write_text("t,pos\n0,0\n0.1,0.001\n")
    (tmp / "cfg.toml").write_text(C4.read_text())
    (tmp / "cfg2.toml").write_text(RCSA.read_text())
    (tmp / "m.csv").write_text("position_m,order,freq_hz\n0.6,1,30\n")
    (tmp / "m_latin1.csv").write_bytes("position_m,order,freq_hz\n0.6,1,30 \u00b5\n".encode("latin-1"))
    (tmp / "m_nan.csv").write_text("position_m,order,freq_hz\n0.6,1,nan\n")
    os.symlink(tmp / "cfg.toml", tmp / "link.csv")
    os.symlink(tmp / "missing-target.csv", tmp / "dangling.csv")
    os.mkfifo(tmp / "fifo.csv")
    (tmp / "sc.csv").write_bytes((D / "traces" / "good.csv").read_bytes())
    os.mkfifo(tmp / "sc.toml")
    (tmp / "wide.csv").write_text("t," + "x" * 1_000_000 + "\n0,1\n")
    (tmp / "done").mkdir()
    for name in ("frf.csv", "report.json"):
        (tmp / "done" / name).write_text("old output\n")
    c4 = C4.read_text()
    (tmp / "subnormal.toml").write_text(c4.replace('lead_m = { value = 0.01,', 'lead_m = { value = 1e-320,'))
    (tmp / "bigint.toml").write_text(c4 + "\n[effects]\nforce_offset_n = " + "9" * 400 + "\n")
    (tmp / "extnan.toml").write_text(c4 + "\n[metadata]\nweight = nan\n")
    (tmp / "noname.toml").write_text(c4.replace('name = "seed004-siemens"', 'name = " "'))
    os.symlink(tmp / "loop", tmp / "loop")
    good = (D / "traces" / "good.csv").read_text().splitlines()
    (tmp / "still.csv").write_text("\n".join([good[0]] + [r.split(",")[0] + ",0" * (len(r.split(",")) - 1)
                                                           for r in good[1:]]) + "\n")
    (tmp / "sc2.csv").write_text("\n".join(good) + "\n")
    epoch = [repr(float(r.split(",", 1)[0]) + 1.7e9) + "," + r.split(",", 1)[1] for r in good[1:]]
    (tmp / "epoch.csv").write_text("\n".join([good[0], *epoch]) + "\n")
    (tmp / "sc2.toml").write_text("axis = 5\n")
    col = good[0].split(",").index("pos_meas")
    inf = [r if i != 4 else ",".join("inf" if j == col else v for j, v in enumerate(r.split(",")))
           for i, r in enumerate(good)]
    (tmp / "inf.csv").write_text("\n".join(inf) + "\n")  # (row 5 of the file: its 4th data row)
    (tmp / "semi.csv").write_text("\n".join(r.replace(",", ";") for r in good) + "\n")
    names = good[0].split(",")
    (tmp / "units.csv").write_text("\n".join([",".join(f"{n} [SI]" for n in names), *good[1:]]) + "\n")
    suffix = {"t": "t_s", "pos_cmd": "pos_cmd_m", "pos_meas": "pos_meas_m", "pos_fb": "pos_fb_m",
              "motor_pos": "motor_pos_rad", "current_q": "current_q_a"}
    (tmp / "suffixes.csv").write_text("\n".join([",".join(suffix.get(n, n + "_x") for n in names), *good[1:]]) + "\n")
    # only pos_meas as a position, named with its unit: the trace has no position column it can read
    keep = [names.index(n) for n in ("t", "pos_cmd", "pos_meas")]
    (tmp / "pos_mm.csv").write_text("\n".join(["t,pos_cmd,pos_meas_mm", *(",".join(r.split(",")[i] for i in keep)
                                                                          for r in good[1:])]) + "\n")
    (tmp / "upper.csv").write_text("\n".join([",".join(n if n == "pos_meas" else n.upper() for n in names),
                                              *good[1:]]) + "\n")
    body = good[1:]
    swapped = body[:9] + [body[10], body[9]] + body[11:]  # lines 1-6: header + 5 rows, blank, then rows on
    (tmp / "blank_unsorted.csv").write_text("\n".join([good[0], *swapped[:5], "", *swapped[5:]]) + "\n")
    gap = body[:9] + body[10:]  # (a sample missing: a gap of two periods from line 11 to 12)
    (tmp / "blank_gap.csv").write_text("\n".join([good[0], *gap[:5], "", *gap[5:]]) + "\n")
    (tmp / "commas.csv").write_text("\n".join([good[0], *body[:7], "," * good[0].count(","), *body[7:]]) + "\n")


def _snapshot(tmp: Path) -> dict[str, bytes | None]:
    """Every file's bytes and every folder (a refused command must not leave an empty output folder either)."""
    return {str(p.relative_to(tmp)): (p.read_bytes() if p.is_file() else None)
            for p in sorted(tmp.rglob("*")) if p.is_file() or p.is_dir()}


@pytest.mark.timeout(60)
@pytest.mark.parametrize("argv,want", [pytest.param(a, w, id=i) for i, a, w in CASES])
def test_bad_input_gives_one_clear_line(tmp_path, capsys, argv, want):
    _setup(tmp_path)
    before = _snapshot(tmp_path)
    rc = main([a.replace("{T}", str(tmp_path)) for a in argv])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2, f"exit {rc}, stderr: {err}"
    assert "Traceback" not in err and "internal error" not in err, err
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    for w in want:
        assert w.replace("{T}", str(tmp_path)) in lines[0], (w, lines[0])
    # nothing was written or changed, and no temporary file was left behind
    assert _snapshot(tmp_path) == before
    assert not [p for p in tmp_path.rglob("*partial*")]


# ---- cases that must succeed, each with its result checked --------------------------------------------------

@pytest.mark.timeout(60)
@pytest.mark.parametrize("name,lead_m,mass_kg,speed_rpm", [
    ("lead_unit_mm", 0.01, 120.0, 3000.0),
    ("mass_unit_g", 0.01, 120.0, 3000.0),
    ("rated_speed_unit_rpm", 0.01, 120.0, 3000.0),
    ("bom", 0.01, 120.0, 3000.0),
    ("crlf", 0.01, 120.0, 3000.0),
])
def test_configs_that_load_correctly(name, lead_m, mass_kg, speed_rpm):
    from virtualaxis.config import load_axis_config

    cfg = load_axis_config(_cfg(name))
    assert cfg.mechanics.lead_m == pytest.approx(lead_m)
    assert cfg.mechanics.table_mass_kg == pytest.approx(mass_kg)
    assert cfg.motor.rated_speed_rpm == pytest.approx(speed_rpm)
    assert cfg == load_axis_config(C4)


@pytest.mark.timeout(120)
def test_profiles_that_run_correctly(tmp_path):
    """A BOM in a move file's header is accepted; chirp with f0 = f1 is a plain sine (no NaN rows)."""
    out = tmp_path / "bom.csv"
    assert main(["simulate", "--config", str(C4), "--profile", _pr("bom.csv"), "--duration", "0.3",
                 "--out", str(out)]) == 0
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == 301
    assert float(rows[-1]["pos_cmd"]) == pytest.approx(0.002, abs=1e-9)
    out2 = tmp_path / "chirp.csv"
    js = tmp_path / "chirp.json"
    assert main(["simulate", "--config", str(C4), "--profile", "chirp:amplitude_um=5,f0_hz=10,f1_hz=10",
                 "--duration", "0.2", "--out", str(out2), "--json", str(js)]) == 0
    rows = list(csv.DictReader(out2.open()))
    cmd = [float(r["pos_cmd"]) for r in rows]
    t = [float(r["t"]) for r in rows]
    import math

    assert all(math.isfinite(float(v)) for r in rows for v in r.values())
    assert max(abs(c - 5e-6 * math.sin(2 * math.pi * 10 * tt)) for c, tt in zip(cmd, t, strict=True)) < 1e-12
    assert json.loads(js.read_text())["simulated_s"] == 0.2
    # --force replaces an existing output; without it the old file is kept
    assert main(["simulate", "--config", str(C4), "--profile", STEP, "--duration", "0.05", "--out", str(out2)]) == 2
    assert len(list(csv.DictReader(out2.open()))) == 201
    assert main(["simulate", "--config", str(C4), "--profile", STEP, "--duration", "0.05", "--out", str(out2),
                 "--force"]) == 0
    assert len(list(csv.DictReader(out2.open()))) == 51
    assert not list(tmp_path.glob(".*partial*"))


@pytest.mark.timeout(60)
@pytest.mark.parametrize("name", ["bom.csv", "crlf.csv"])
def test_traces_that_read_correctly(name):
    from virtualaxis.diagnosis.trace import read_trace

    ref = read_trace(_tr("good.csv"))
    tr = read_trace(_tr(name))
    assert tr.columns.keys() == ref.columns.keys()
    for k in ref.columns:
        assert (tr.columns[k] == ref.columns[k]).all()


@pytest.mark.timeout(60)
def test_truncated_last_row_is_dropped_with_a_warning():
    from virtualaxis.diagnosis.trace import read_trace

    ref = read_trace(_tr("good.csv"))
    tr = read_trace(_tr("truncated_last_row.csv"))
    assert tr.t.size == ref.t.size - 1
    assert any("truncated" in w and f"line {ref.t.size + 1}" in w for w in tr.warnings), tr.warnings


@pytest.mark.timeout(60)
def test_internal_error_is_one_line_and_debug_shows_traceback(capsys, monkeypatch):
    """The last resort: an unexpected exception is one line, exit 1; --debug adds the traceback."""
    import virtualaxis.cli.modal as modal

    def boom(args):
        raise RuntimeError("unexpected\nmulti-line")

    monkeypatch.setattr(modal, "run", boom)
    from virtualaxis.cli import main as main_mod

    parser = main_mod.build_parser()
    monkeypatch.setattr(main_mod, "build_parser", lambda: parser)
    parser._subparsers._group_actions[0].choices["modal"].set_defaults(func=boom)
    assert main(["modal", "--config", str(C4)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("internal error in 'modal': RuntimeError: unexpected multi-line")
    assert main(["--debug", "modal", "--config", str(C4)]) == 1
    assert "Traceback" in capsys.readouterr().err
