"""Two nodes with one node-ID on one bus: each node sees the other's boot-up, heartbeat and SDO answers on COB-IDs
that only it should send, counts them (0x2100:29) and says once what is wrong."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import time

import can
import canopen
from served_drive import CLI, ROOT, served

from virtualaxis.canopen_slave import CanopenSlave
from virtualaxis.canopen_slave.testing import EDS_PATH, MasterRig, SlaveRunner, wait_until

NODE = 12


def test_a_second_node_with_the_same_id_is_counted_and_named_once(caplog):
    caplog.set_level(logging.WARNING, logger="virtualaxis.canopen_slave")
    with MasterRig(NODE) as rig:
        first = rig.slave
        assert wait_until(lambda: rig.sniffer.of(0x700 + NODE))  # the first node's boot-up
        assert first.counters["node_id_conflicts"] == 0
        bus = can.Bus(interface="virtual", channel=rig.channel)
        second = CanopenSlave(bus, NODE, EDS_PATH)
        notifier = can.Notifier(bus, [second.listener()], timeout=0.01)
        runner = SlaveRunner(second).start()  # its boot-up reaches the first node
        try:
            assert wait_until(lambda: first.counters["node_id_conflicts"] == 1)
            rig.node.sdo.upload(0x1000, 0)  # both answer: each node sees the other's answer
            assert wait_until(lambda: first.counters["node_id_conflicts"] == 2)
            assert wait_until(lambda: second.counters["node_id_conflicts"] == 1)
            rig.node.sdo.upload(0x1000, 0)
            assert wait_until(lambda: second.counters["node_id_conflicts"] == 2)
            # the count is in the object dictionary; the warning was said once per node
            assert runner.call(first.read, 0x2100, 29) == first.counters["node_id_conflicts"]
            said = [r.getMessage() for r in caplog.records if "another node on this bus" in r.getMessage()]
            assert len(said) == 2, said
            assert f"node {NODE}: another node on this bus has node-ID {NODE}" in said[0]
            assert "a boot-up or heartbeat on COB-ID 0x70C" in said[0]
            assert "an SDO answer on COB-ID 0x58C" in said[1]
            assert first.counters["malformed_frames"] == second.counters["malformed_frames"] == 0
        finally:
            runner.stop()
            notifier.stop()
            bus.shutdown()


def test_one_node_alone_counts_no_conflict_with_its_own_frames():
    """A node's own boot-up, heartbeats and SDO answers are not taken for another node's."""
    with MasterRig(NODE) as rig:
        rig.node.sdo[0x1017].raw = 10  # heartbeat every 10 ms
        for _ in range(20):
            rig.node.sdo.upload(0x1000, 0)
        assert wait_until(lambda: len(rig.sniffer.of(0x700 + NODE)) >= 10)
        assert rig.slave.counters["node_id_conflicts"] == 0


def test_two_serves_with_one_node_id_both_say_so(tmp_path):
    """Through the user's door: `virtualaxis serve --node-id 7` twice on one bus (two processes)."""
    with served("--node-id", "7", "--json", str(tmp_path / "first.json")) as first:
        second = subprocess.Popen(
            [*CLI, "serve", "--can", first.spec, "--node-id", "7", "--status-interval", "0",
             "--json", str(tmp_path / "second.json")],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
            env={**os.environ, "PYTHONUNBUFFERED": "1"})
        try:
            assert second.stdout.readline().startswith("ready:")
            net = canopen.Network()
            net.connect(**first.bus_kwargs())
            try:
                node = net.add_node(7, os.path.join(ROOT, "eds", "virtualaxis.eds"))
                node.sdo.RESPONSE_TIMEOUT = 5.0
                node.sdo.upload(0x1000, 0)  # answered twice
                time.sleep(0.5)
            finally:
                net.disconnect()
            # the conformance suite names the clash instead of judging whichever answer comes first
            conf = subprocess.run([*CLI, "conformance", "--can", first.spec, "--node-id", "7", "--pacing", "realtime"],
                                  capture_output=True, text=True, cwd=ROOT, timeout=120)
        finally:
            second.terminate()
            out, err = second.communicate(timeout=30)
    for stderr, name in ((first.stderr, "first.json"), (err, "second.json")):
        assert stderr.count("another node on this bus has node-ID 7") == 1, stderr
        counters = json.loads((tmp_path / name).read_text())
        assert counters["axes"][0]["canopen"]["node_id_conflicts"] >= 1, counters
    assert "Traceback" not in first.stderr + err
    assert conf.returncode == 2, conf.stdout + conf.stderr
    assert "2 answers on COB-ID 0x587 to one SDO request: more than one node on this bus has node-ID 7" in conf.stderr
    assert "Traceback" not in conf.stderr


def test_conformance_against_one_node_sees_one_answer():
    """The same check with one node: no clash named, the checks run."""
    with served("--node-id", "7") as one:
        conf = subprocess.run([*CLI, "conformance", "--can", one.spec, "--node-id", "7", "--pacing", "realtime",
                               "--only", "301-ID-1"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert "answers on COB-ID" not in conf.stderr
    assert "summary: 1 checks, 1 passed" in conf.stdout, conf.stdout + conf.stderr


