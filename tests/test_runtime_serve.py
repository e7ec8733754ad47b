"""The runtime: bus strings, `virtualaxis serve` in a separate process over udp_multicast (hop_limit 0) under
a canopen master, real-time pacing bookkeeping, CLI errors."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import canopen
import pytest
from test_drive_rig import Rig, seed_config, seed_discrete

from virtualaxis.drive.core import DEFAULT_EDS
from virtualaxis.runtime import AxisNode, BusOpenError, Runtime, open_bus, parse_bus_spec

pytestmark = pytest.mark.exclusive  # timing-sensitive: background jobs stopped meanwhile


def test_bus_spec_parsing():
    assert parse_bus_spec("socketcan:vcan0") == ("socketcan", "vcan0", {})
    assert parse_bus_spec("udp_multicast:ff15:7079::1,port=43113,hop_limit=1") == (
        "udp_multicast",
        "ff15:7079::1",
        {"port": 43113, "hop_limit": 1},
    )
    with pytest.raises(BusOpenError, match="INTERFACE:CHANNEL"):
        parse_bus_spec("vcan0")
    with pytest.raises(BusOpenError, match="key=value"):
        parse_bus_spec("virtual:x,nonsense")


def test_udp_multicast_is_opened_with_hop_limit_zero():
    bus = open_bus("udp_multicast:239.74.163.2,port=43991")
    try:
        import socket

        sock = bus._multicast._socket
        assert sock.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL) == 0
    finally:
        bus.shutdown()


def test_missing_socketcan_says_how_to_create_vcan_and_how_to_use_udp():
    try:
        bus = open_bus("socketcan:vcan_va_missing")
    except BusOpenError as exc:
        msg = str(exc)
        assert "ip link add dev vcan_va_missing type vcan" in msg and "ip link set up" in msg
        assert "udp_multicast" in msg
    else:  # a machine with this interface (never expected)
        bus.shutdown()
        pytest.skip("socketcan interface exists here")


# (not `python -m virtualaxis.cli.main`: that imports cli.main twice and its CliError would not be caught)
CLI = [sys.executable, "-c", "import sys; from virtualaxis.cli.main import main; sys.exit(main())"]


def _virtualaxis(*args: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=60, **kw)


def test_serve_cli_errors_are_one_line():
    r = _virtualaxis("serve", "--can", "socketcan:vcan_va_missing", "--duration", "1")
    assert r.returncode == 2 and r.stderr.startswith("error: ") and "Traceback" not in r.stderr
    assert "udp_multicast" in r.stderr
    r = _virtualaxis("serve", "--can", "virtual:x", "--axis", "X=1")
    assert r.returncode == 2 and "NAME=ID:CONFIG" in r.stderr
    r = _virtualaxis("serve", "--can", "virtual:x", "--config", "nope.toml")
    assert r.returncode == 2 and "nope.toml" in r.stderr and "file not found" in r.stderr
    r = _virtualaxis(
        "serve",
        "--can",
        "virtual:x",
        "--axis",
        "X=1:configs/seed000-hust.toml",
        "--axis",
        "Y=1:configs/seed000-hust.toml",
    )
    assert r.returncode == 2 and "node id" in r.stderr


@pytest.fixture
def served_process():
    """`virtualaxis serve` with two axes (X=1, Y=2) in lockstep, in its own process on udp_multicast."""
    port = 44000 + os.getpid() % 1000
    spec = f"udp_multicast:239.74.163.2,port={port}"
    cfg = "configs/seed000-hust.toml"
    proc = subprocess.Popen(
        [
            *CLI,
            "serve",
            "--can",
            spec,
            "--axis",
            f"X=1:{cfg}",
            "--axis",
            f"Y=2:{cfg}",
            "--lockstep",
            "--status-interval",
            "0",
            "--duration",
            "60",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
        cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
    )
    line = proc.stdout.readline()
    if not line.startswith("ready:"):
        proc.kill()
        raise AssertionError(f"serve did not start: {line!r} {proc.stderr.read()}")
    yield proc, spec
    proc.terminate()
    proc.wait(timeout=10)


def test_two_axes_served_by_another_process_over_udp_multicast(served_process):
    """A master in this process drives both axes of the `serve` process: boot, SDO, NMT, state machine,
    a small synchronous move on each axis, lockstep SYNC counting."""
    proc, spec = served_process
    net = canopen.Network()
    net.connect(interface="udp_multicast", channel="239.74.163.2", port=int(spec.rsplit("=", 1)[1]), hop_limit=0)
    try:
        nodes = {}
        for nid in (1, 2):
            node = canopen.BaseNode402(nid, str(DEFAULT_EDS))
            node.sdo.RESPONSE_TIMEOUT = 2.0
            net.add_node(node)
            node.sdo[0x1017].raw = 50
            node.nmt.wait_for_heartbeat(5.0)
            assert node.sdo[0x6041].raw & 0x4F == 0x40
            node.sdo[0x6060].raw = 8
            node.rpdo.read()
            node.rpdo[2].trans_type = 1
            node.rpdo[2].save()
            node.nmt.state = "OPERATIONAL"
            for cw in (0x06, 0x07, 0x0F):
                node.sdo[0x6040].raw = cw
            assert node.sdo[0x6041].raw & 0x6F == 0x27
            nodes[nid] = node
        # closed loop: each SYNC waits for the synchronous TPDO2 of both axes (no frame piles up even when
        # the machine is loaded)
        counts = {1: [0], 2: [0]}
        for nid, node in nodes.items():
            node.tpdo.read()
            node.tpdo[2].trans_type = 1
            node.tpdo[2].save()
            node.tpdo[2].add_callback(lambda m, c=counts[nid]: c.__setitem__(0, c[0] + 1))

        def sync_and_wait(k: int) -> None:
            net.sync.transmit()
            end = time.monotonic() + 5.0
            while min(counts[1][0], counts[2][0]) < k:
                assert time.monotonic() < end, "no TPDO for a SYNC"
                time.sleep(100e-6)

        for k in range(1, 401):
            for nid, node in nodes.items():
                node.rpdo[2]["Controlword"].raw = 0x0F
                node.rpdo[2]["Target position"].raw = nid * 10 * min(k, 300)  # X to 3 mm, Y to 6 mm
                node.rpdo[2].transmit()
            sync_and_wait(k)
        assert abs(nodes[1].sdo[0x6064].raw - 3000) < 20
        assert abs(nodes[2].sdo[0x6064].raw - 6000) < 20
        assert nodes[1].sdo[0x2100][13].raw == nodes[2].sdo[0x2100][13].raw == 400  # SYNC received
    finally:
        net.disconnect()


def test_real_time_mode_runs_every_cycle_and_counts_late_ones():
    """Real-time pacing: the plant time equals the wall time (late cycles are run, and counted as
    overruns when more than one period late - never skipped silently)."""
    r = Rig(lockstep=False)
    try:
        drive = r.drive
        time.sleep(0.3)
        # 0x2110:2 is the live overrun counter: the SDO answer lies between the counter read before and after it
        # (the runtime keeps running while the request travels; equality would race under load)
        before = drive.counters["overruns"] & 0xFFFFFFFF
        via_sdo = r.node.sdo[0x2110][2].raw
        after = drive.counters["overruns"] & 0xFFFFFFFF
        assert before <= via_sdo <= after
    finally:
        r.close()
    stats = r.runtime.stats
    period = drive.cycle_s
    # every deadline of the schedule was either run or counted as given up - none disappears silently
    assert stats.cycles + stats.skipped == round((stats.next_deadline_s - stats.first_deadline_s) / period)
    assert stats.overruns >= stats.skipped
    assert stats.cycles + stats.skipped >= 250  # >= 0.3 s of 1 ms deadlines
    assert drive.counters["cycles"] >= stats.cycles  # (plus the SYNC-free boot cycles: none here)
    assert stats.overruns == drive.counters["overruns"]  # (the cycles given up are overruns too)


def test_real_time_cycles_given_up_are_counted_as_overruns_by_the_runtime_and_the_drive():
    """A loop stalled for longer than ``max_lag_s`` gives the missed cycles up (``skipped``); they are overruns
    in the runtime's statistics (serve's JSON) as in the drive's 0x2110:2, one count each."""
    bus = open_bus(f"virtual:va-skip-{os.getpid()}-{time.monotonic_ns()}")
    rt = Runtime(bus, [AxisNode(bus, 1, seed_config(), discrete=seed_discrete(), name="A1")], max_lag_s=0.05)
    drive = rt.axes[0].drive
    rt.start()
    try:
        time.sleep(0.1)
        stalled = threading.Event()
        rt.run_in_gap(lambda: (time.sleep(0.3), stalled.set()))  # the runtime thread held for 0.3 s
        assert stalled.wait(10.0)
        time.sleep(0.1)
    finally:
        rt.stop()
    stats = rt.stats
    assert stats.skipped >= 200, stats.skipped  # ~250 of the 300 cycles of the stall given up
    assert stats.overruns >= stats.skipped
    assert drive.counters["overruns"] == stats.overruns
