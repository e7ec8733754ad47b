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


def test_unit_ids_0_and_255_address_the_single_served_axis():
    """`virtualaxis serve --modbus` in a subprocess, a pymodbus client: units 0 and 255 read and write the axis
    served as node 5 and get an answer; an unknown unit id still gets exception 0B."""
    from pymodbus.client import ModbusTcpClient
    from services_fixtures import free_port, wait_port

    port = free_port()
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    cli = [sys.executable, "-c", "import sys; from virtualaxis.cli.main import main; sys.exit(main())"]
    proc = subprocess.Popen(
        [*cli, "serve", "--can", f"udp_multicast:239.74.163.9,port={free_port()}", "--node-id", "5",
         "--modbus", f"127.0.0.1:{port}", "--modbus-writable", "--status-interval", "0"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=3)
    try:
        wait_port(port, timeout_s=120)
        assert client.connect()
        mode = 40102 - 40001
        for unit in (0, 255):
            r = client.read_holding_registers(mode, count=1, device_id=unit)
            assert not r.isError(), (unit, r)
        w = client.write_register(mode, 3, device_id=0)
        assert not w.isError(), w
        assert client.read_holding_registers(mode, count=1, device_id=5).registers == [3]
        w = client.write_register(mode, 1, device_id=255)
        assert not w.isError(), w
        assert client.read_holding_registers(mode, count=1, device_id=0).registers == [1]
        r = client.read_holding_registers(mode, count=1, device_id=6)
        assert r.isError() and r.exception_code == 0x0B
    finally:
        client.close()
        proc.terminate()
        proc.wait(timeout=30)


def test_units_0_and_255_name_no_axis_when_several_are_served():
    from virtualaxis.services.modbus_units import resolve_unit

    assert resolve_unit(0, [5]) == 5 and resolve_unit(255, [5]) == 5 and resolve_unit(7, [5]) == 7
    assert resolve_unit(0, [1, 2]) == 0 and resolve_unit(255, [1, 2]) == 255
    assert resolve_unit(255, [255]) == 255
