"""301-EDS-1 reads every object the EDS lists and writes the rw ones back: it must leave the node as it found it
(an injected fault stays: the fault-injection channel's command objects are not written back) and judge the size
the node answers with, not the size the master's library cuts the answer to. ``virtualaxis conformance`` in a
subprocess against ``virtualaxis serve`` (udp_multicast, hop_limit 0)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from virtualaxis.master import DEFAULT_EDS
from virtualaxis.testing import start_virtual_axis

pytestmark = pytest.mark.exclusive  # timing-sensitive: background jobs stopped meanwhile

CLI = [sys.executable, "-c", "import sys; from virtualaxis.cli.main import main; sys.exit(main())"]


def _eds_check(axis, tmp_path: Path, eds: Path | None = None) -> dict:
    js = tmp_path / "c.json"
    args = [*CLI, "conformance", "--can", axis.bus_spec, "--node-id", str(axis.node_id), "--pacing", "lockstep",
            "--only", "301-EDS-1", "--json", str(js), "--force"]
    if eds is not None:
        args += ["--eds", str(eds)]
    proc = subprocess.run(args, capture_output=True, text=True, timeout=300)
    assert js.exists(), proc.stdout[-2000:] + proc.stderr[-2000:]
    (check,) = json.loads(js.read_text())["checks"]
    return check


def test_the_write_back_leaves_an_injected_fault_in_place(tmp_path):
    with start_virtual_axis(transport="udp", lockstep=True) as axis:
        injector = axis.injectors[axis.node_id]
        injector.inject("safe_torque_off")
        assert injector.active == ["safe_torque_off"]
        check = _eds_check(axis, tmp_path)
        assert check["status"] == "pass", check
        assert injector.active == ["safe_torque_off"]  # not cleared by writing 0x5FF1 = 0 back
        assert axis.nodes[axis.node_id].sdo[0x603F].raw == 0x5400


def test_an_answer_longer_than_the_eds_data_type_is_named(tmp_path):
    """An EDS that gives 0x6064 as INTEGER16 where the node answers 4 bytes: the canopen library cuts the answer
    to 2 bytes; the check reads the size the node indicated."""
    text = Path(DEFAULT_EDS).read_text()
    head = text.index("[6064]")
    section = text[head:text.index("\n[", head + 1)]
    assert "DataType=0x0004" in section
    eds = tmp_path / "pos_int16.eds"
    eds.write_text(text.replace(section, section.replace("DataType=0x0004", "DataType=0x0003")))
    with start_virtual_axis(transport="udp", lockstep=True) as axis:
        check = _eds_check(axis, tmp_path, eds)
    assert check["status"] == "fail", check
    assert "0x6064:0" in check["detail"] and "4 bytes, EDS data type 0x0003 has 2" in check["detail"], check


def test_a_failure_on_a_node_left_in_fault_says_so(tmp_path):
    """A persistent fault (encoder loss injected before the run: it survives the suite's NMT reset) stops every
    move; the failure message of a move check says what the statusword tells, FAULT with its error code, beside
    the behaviour it missed."""
    with start_virtual_axis(transport="udp", lockstep=True) as axis:
        axis.injectors[axis.node_id].inject("encoder_loss")
        js = tmp_path / "pp.json"
        subprocess.run([*CLI, "conformance", "--can", axis.bus_spec, "--node-id", str(axis.node_id), "--pacing",
                        "lockstep", "--only", "402-PP-1", "--json", str(js)], capture_output=True, text=True,
                       timeout=300)
    (check,) = json.loads(js.read_text())["checks"]
    assert check["status"] == "fail", check
    assert "after the check the node shows FAULT (statusword 0x" in check["detail"], check
    assert "error code 0x603F = 0x7305" in check["detail"], check
