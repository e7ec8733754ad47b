"""``conformance`` and ``fault`` against a node whose SDO server misbehaves: a raw-frame responder in this
process on a host-local ``udp_multicast`` bus (hop_limit=0), the CLI in a subprocess. A segmented upload whose
segments never end, or stop coming, ends the run with one ``error:`` line (an error of the run, not a failed
check) within a bound derived from ``--sdo-timeout``; short frames are one ``error:`` line of ``fault``."""

from __future__ import annotations

import os
import random
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import can
import pytest

from virtualaxis.runtime import open_bus

ROOT = Path(__file__).resolve().parents[1]
NODE = 5
DEVICE_TYPE_402 = 0x00020192


class Responder(threading.Thread):
    """Answers SDO requests to node :data:`NODE`: 0x1000 expedited, every other upload as ``mode`` says:

    - ``endless``: a segmented upload whose segments never end (each segment request answered, never the last);
    - ``silent``: the initiate answered (segmented, 100 bytes), then no segment ever;
    - ``short``: every request answered with a 3-byte frame.

    Downloads are refused (abort 0x06010002), block transfers too (0x05040001)."""

    def __init__(self, spec: str, mode: str):
        super().__init__(daemon=True)
        self.bus = open_bus(spec)
        self.mode = mode
        self.stop = threading.Event()
        self.segments = 0

    def _send(self, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=0x580 + NODE, data=data, is_extended_id=False))

    def _abort(self, req: bytes, code: int) -> None:
        self._send(bytes((0x80,)) + req[1:4] + struct.pack("<L", code))

    def run(self) -> None:
        while not self.stop.is_set():
            msg = self.bus.recv(0.05)
            if msg is None or msg.arbitration_id != 0x600 + NODE or msg.dlc < 1:
                continue
            req = bytes(msg.data).ljust(8, b"\0")
            ccs = req[0] >> 5
            index = req[1] | req[2] << 8
            if self.mode == "short":
                self._send(bytes((0x43, req[1], req[2])))
            elif ccs == 2 and index == 0x1000:
                self._send(bytes((0x43,)) + req[1:4] + struct.pack("<L", DEVICE_TYPE_402))
            elif ccs == 2:
                self._send(bytes((0x41,)) + req[1:4] + struct.pack("<L", 100))
            elif ccs == 3:
                self.segments += 1
                if self.mode == "endless":
                    self._send(bytes((req[0] & 0x10,)) + b"segment")
            elif ccs == 1:
                self._abort(req, 0x06010002)
            elif ccs in (5, 6):
                self._abort(req, 0x05040001)

    def close(self) -> None:
        self.stop.set()
        self.join(2)
        self.bus.shutdown()


@pytest.fixture
def bus_spec():
    group = f"239.{random.randint(1, 254)}.{random.randint(1, 254)}.{random.randint(1, 254)}"
    return f"udp_multicast:{group},port={random.randint(20000, 60000)}"


def _cli(args: list[str], cwd: Path, timeout_s: float) -> tuple[subprocess.CompletedProcess, float]:
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src") + os.pathsep + os.environ.get("PYTHONPATH", "")}
    t0 = time.monotonic()
    res = subprocess.run([sys.executable, "-m", "virtualaxis.cli.main", *args], capture_output=True, text=True,
                         env=env, cwd=cwd, timeout=timeout_s)
    return res, time.monotonic() - t0


@pytest.mark.timeout(240)
@pytest.mark.parametrize("mode", ["endless", "silent"])
def test_conformance_run_against_a_broken_sdo_server_ends_with_a_run_error(tmp_path, bus_spec, mode):
    sdo_timeout_s = 0.5
    node = Responder(bus_spec, mode)
    node.start()
    try:
        # generous bound: start-up (imports, bus) + 20 unanswered exchanges or one 10-timeout transfer + the
        # checks that pass quickly, on a loaded 2-core host
        res, elapsed = _cli(["conformance", "--can", bus_spec, "--node-id", str(NODE), "--sdo-timeout",
                             str(sdo_timeout_s), "--json", "r.json"], tmp_path, timeout_s=200)
    finally:
        node.close()
    assert elapsed < 30 + 60 * sdo_timeout_s, f"{elapsed:.0f} s"
    err = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2, (res.stdout[-2000:], res.stderr)
    assert len(err) == 1 and err[0].startswith("error: node 5: "), res.stderr
    assert "SDO server" in err[0] and "the run stopped" in err[0], err[0]
    assert "Traceback" not in res.stderr and "internal error" not in res.stderr
    assert not (tmp_path / "r.json").exists()
    if mode == "endless":
        assert node.segments > 3  # the node kept sending: the transfer was cut, not failed on its first segment


@pytest.mark.timeout(120)
@pytest.mark.parametrize("action", ["status", "list"])
def test_fault_against_a_node_answering_short_frames_is_one_error_line(tmp_path, bus_spec, action):
    node = Responder(bus_spec, "short")
    node.start()
    try:
        res, _ = _cli(["fault", "--can", bus_spec, "--node-id", str(NODE), "--timeout", "0.5", action], tmp_path,
                      timeout_s=100)
    finally:
        node.close()
    err = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2, res.stderr
    assert len(err) == 1 and err[0].startswith("error: node 5 "), res.stderr
    assert "3 byte(s)" in err[0], err[0]
    assert "Traceback" not in res.stderr and "internal error" not in res.stderr
