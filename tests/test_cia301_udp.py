"""Across processes: a bare CiA 301 node in a child process, a canopen master here, over python-can
udp_multicast (hop_limit=0, loopback only)."""

from __future__ import annotations

import os
import random
import struct
import subprocess
import sys
import time

import can
import canopen
import pytest

from virtualaxis.canopen_slave.testing import EDS_PATH, Sniffer

NODE = 21


@pytest.fixture
def udp_node():
    rng = random.Random(os.getpid() ^ int(time.time() * 1000))
    channel = f"239.74.{rng.randint(100, 250)}.{rng.randint(1, 250)}"
    port = rng.randint(44000, 46000)
    proc = subprocess.Popen(
        [sys.executable, "-m", "virtualaxis.canopen_slave.testing", "--interface", "udp_multicast",
         "--channel", channel, "--port", str(port), "--node-id", str(NODE), "--seconds", "30",
         "--counting-position"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line.strip() == "ready", proc.stderr.read()
        bus = can.Bus(interface="udp_multicast", channel=channel, port=port, hop_limit=0)
        sniffer = Sniffer()
        network = canopen.Network(bus)
        network.NOTIFIER_CYCLE = 0.01
        network.connect()
        network.notifier.add_listener(sniffer)
        node = canopen.RemoteNode(NODE, str(EDS_PATH))
        network.add_node(node)
        yield network, node, sniffer
        network.disconnect()
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def test_master_in_another_process(udp_node):
    network, node, sniffer = udp_node
    assert node.sdo[0x1000].raw == 0x00020192                               # expedited
    assert node.sdo[0x1008].raw == "virtualaxis servo drive"                 # segmented
    with node.sdo[0x1018][2].open("rb", block_transfer=True) as f:           # block upload
        assert struct.unpack("<I", f.read())[0] == 0x402
    with node.sdo[0x6081].open("wb", block_transfer=True, size=4) as f:      # block download
        f.write(struct.pack("<I", 31337))
    assert node.sdo[0x6081].raw == 31337
    node.sdo[0x1017].raw = 20
    assert node.nmt.wait_for_heartbeat(timeout=1.0) == "PRE-OPERATIONAL"
    node.nmt.state = "OPERATIONAL"
    assert node.nmt.wait_for_heartbeat(timeout=1.0) in ("PRE-OPERATIONAL", "OPERATIONAL")
    time.sleep(0.05)
    sniffer.clear()
    for _ in range(20):
        network.sync.transmit()
        time.sleep(0.01)
    frames = sniffer.wait_for(0x280 + NODE, 20, timeout_s=2.0)
    assert len(frames) == 20
    positions = [struct.unpack_from("<i", d, 2)[0] for _t, d in frames]
    assert positions == list(range(positions[0], positions[0] + 20))
    with pytest.raises(canopen.SdoAbortedError) as info:
        node.sdo.upload(0x5555, 0)
    assert info.value.code == 0x06020000
