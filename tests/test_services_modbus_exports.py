"""The register map for import (docs/modbus-map.csv, docs/modbus-map.json): generated from the same data as
docs/modbus-map.md, parseable by the standard csv / json readers, and printed by the generator's command line."""

from __future__ import annotations

import csv
import io
import json
import os
import subprocess
import sys
from pathlib import Path

from virtualaxis.services.modbus_map import REGISTERS, render_csv, render_json

ROOT = Path(__file__).resolve().parents[1]
GENERATOR = [sys.executable, "-m", "virtualaxis.services.modbus_map"]


def _run(*args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    return subprocess.run([*GENERATOR, *args], capture_output=True, text=True, env=env, timeout=120)


def test_csv_and_json_maps_are_generated_from_the_map():
    for name, render in (("modbus-map.csv", render_csv), ("modbus-map.json", render_json)):
        assert (ROOT / "docs" / name).read_text() == render(), (
            f"docs/{name} differs from the register map: run "
            f"`python3 -m virtualaxis.services.modbus_map --write docs/{name}`")


def test_csv_and_json_rows_describe_every_register():
    rows = list(csv.DictReader(io.StringIO((ROOT / "docs" / "modbus-map.csv").read_text())))
    doc = json.loads((ROOT / "docs" / "modbus-map.json").read_text())
    assert len(rows) == len(doc["registers"]) == len(REGISTERS)
    for row, js, reg in zip(rows, doc["registers"], REGISTERS, strict=True):
        assert int(row["register"]) == js["register"] == reg.number
        assert int(row["address"]) == js["address"] == reg.number - 40001
        assert int(row["words"]) == js["words"] == (2 if reg.dtype in ("u32", "i32") else 1)
        assert row["name"] == js["name"] == reg.name and row["type"] == js["type"] == reg.dtype
        assert row["access"] == js["access"] == ("RW" if reg.write is not None else "R")
        assert int(row["min"]) == js["min"] and int(row["max"]) == js["max"] and js["min"] < js["max"]
    md = (ROOT / "docs" / "modbus-map.md").read_text()
    assert "modbus-map.csv" in md and "modbus-map.json" in md


def test_generator_prints_each_format_and_refuses_an_unknown_suffix(tmp_path):
    out = _run("--format", "csv")
    assert out.returncode == 0 and out.stdout == render_csv()
    out = _run("--format", "json")
    assert out.returncode == 0 and json.loads(out.stdout)["registers"]
    bad = _run("--write", str(tmp_path / "map.txt"))
    assert bad.returncode == 2 and bad.stderr.startswith("error: --write") and "Traceback" not in bad.stderr
    assert not (tmp_path / "map.txt").exists()
