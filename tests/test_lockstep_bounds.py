"""SYNC lockstep: drive time per SYNC is the declared communication cycle (0x1006), bounded; a pass whose
cycles keep the node from answering longer than ``--stall-s`` makes the run unhealthy. `virtualaxis serve
--lockstep` in a child process, a `canopen` master in this one (udp_multicast, hop_limit 0)."""

from __future__ import annotations

import json
import time

import canopen
import pytest
from served_drive import served

from virtualaxis.master import DEFAULT_EDS, connect

MAX_PERIOD_US = 100_000  # the documented bound of 0x1006 in lockstep (docs/drive.md)


def _send_sync(net: canopen.Network) -> None:
    net.send_message(0x80, b"")


def test_lockstep_refuses_a_communication_cycle_beyond_its_bound_and_keeps_answering(tmp_path):
    out = tmp_path / "serve.json"
    with served("--lockstep", "--json", str(out)) as s:
        net = connect(s.spec)
        try:
            node = canopen.RemoteNode(1, DEFAULT_EDS)
            net.add_node(node)
            node.sdo.RESPONSE_TIMEOUT = 2.0
            for too_long_us in (0xFFFFFFFF, 10_000_000, MAX_PERIOD_US + 1):
                with pytest.raises(canopen.SdoAbortedError) as err:
                    node.sdo[0x1006].raw = too_long_us
                assert err.value.code == 0x06090031, hex(err.value.code)
            node.sdo[0x1006].raw = MAX_PERIOD_US  # the bound itself is served
            _send_sync(net)
            t0 = time.perf_counter()
            assert node.sdo[0x1006].raw == MAX_PERIOD_US
            answered_s = time.perf_counter() - t0
            assert answered_s < 1.0, f"SDO answered {answered_s:.3f} s after the SYNC"
        finally:
            net.disconnect()
        assert s.stop() == 0, s.stderr
    summary = json.loads(out.read_text())
    assert summary["healthy"] is True and summary["stalls"] == 0
    assert summary["runtime"]["syncs"] == 1
    assert summary["runtime"]["cycles"] == MAX_PERIOD_US // 1000  # 1 ms position cycle of the seed config


def test_a_stalled_lockstep_cycle_makes_the_run_unhealthy(tmp_path):
    out = tmp_path / "serve.json"
    with served("--lockstep", "--stall-s", "0.0001", "--json", str(out)) as s:
        net = connect(s.spec)
        try:
            node = canopen.RemoteNode(1, DEFAULT_EDS)
            net.add_node(node)
            node.sdo.RESPONSE_TIMEOUT = 2.0
            node.sdo[0x1006].raw = MAX_PERIOD_US
            _send_sync(net)
            assert node.sdo[0x1006].raw == MAX_PERIOD_US  # answered once the cycles are done
        finally:
            net.disconnect()
        code = s.stop()
    summary = json.loads(out.read_text())
    assert summary["stalls"] == 1 and summary["healthy"] is False
    assert summary["runtime"]["max_sync_work_ms"] > 0.1
    assert code == 1 and "error: the lockstep cycle stalled 1 time(s)" in s.stderr and "Traceback" not in s.stderr


def test_stall_option_needs_lockstep():
    import subprocess

    from served_drive import CLI

    r = subprocess.run([*CLI, "serve", "--can", "virtual:x", "--stall-s", "1", "--duration", "1"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.startswith("error: --stall-s") and "Traceback" not in r.stderr
