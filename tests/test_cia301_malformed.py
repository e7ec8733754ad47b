"""Malformed and hostile frames: counted, answered as a drive answers, and the node keeps running."""

from __future__ import annotations

import random
import struct
import time

from virtualaxis.canopen_slave.testing import MasterRig, RecordingApp, wait_until

NODE = 17


def test_wrong_dlc_frames_are_counted_and_ignored():
    with MasterRig(NODE) as rig:
        rig.node.nmt.state = "OPERATIONAL"
        rig.send(0x600 + NODE, b"\x40\x00\x10\x00")            # SDO with DLC 4: ignored (client times out)
        rig.send(0x600 + NODE, b"")
        rig.send(0x700 + NODE, b"\x05")                          # a heartbeat of another node with our id
        rig.send(0x000, b"\x01")                                 # NMT DLC 1
        rig.send(0x80, b"\x01\x02\x03")                          # SYNC with data while 0x1019 = 0
        assert rig.sniffer.wait_for(0x80 + NODE, match=lambda d: d[:2] == b"\x40\x82")
        c = rig.slave.counters
        assert wait_until(lambda: c["malformed_frames"] == 4)
        assert c["node_id_conflicts"] == 1
        assert c["sdo_requests"] == 0 and c["sync_length_errors"] == 1
        time.sleep(0.05)
        assert rig.sniffer.of(0x580 + NODE) == []
        assert rig.node.sdo[0x1000].raw == 0x00020192
        assert struct.unpack("<I", rig.node.sdo.upload(0x2100, 1))[0] == c["malformed_frames"]


def test_random_frames_never_stop_the_node():
    """Thousands of random frames on every COB-ID the node listens to, then it still answers correctly."""
    app = RecordingApp()
    rng = random.Random(20261122)
    with MasterRig(NODE, app=app) as rig:
        app.slave = rig.slave
        rig.node.sdo[0x1016][1].raw = (0x33 << 16) | 1000
        ids = [0x000, 0x080, 0x200 + NODE, 0x300 + NODE, 0x400 + NODE, 0x500 + NODE, 0x600 + NODE,
               0x700 + NODE, 0x733]
        for i in range(3000):
            cob = rng.choice(ids)
            length = 8 if cob == 0x600 + NODE and rng.random() < 0.8 else rng.randint(0, 8)
            data = bytes(rng.getrandbits(8) for _ in range(length))
            if cob == 0x000 and len(data) == 2 and data[0] in (0x02, 0x81, 0x82):
                data = bytes((0x80, data[1]))                    # keep it answering SDO (no stop/resets)
            rig.send(cob, data, remote=(cob == 0x700 + NODE and i % 7 == 0))
            if i % 50 == 0:
                time.sleep(0.002)                                 # let the receive queue drain
        assert wait_until(lambda: rig.slave.counters["frames_received"] >= 3000, 5.0)
        time.sleep(1.2)                                           # any half-open transfer times out
        rig.send(0x000, bytes((0x80, NODE)))
        assert wait_until(lambda: int(rig.slave.nmt_state) == 127)
        node = rig.node
        time.sleep(0.05)
        while not node.sdo.responses.empty():                   # answers to the random requests
            node.sdo.responses.get_nowait()
        assert node.sdo[0x1000].raw == 0x00020192
        assert node.sdo[0x1008].raw == "virtualaxis servo drive"
        c = rig.slave.counters
        assert c["internal_errors"] == 0
        assert c["rx_overruns"] == 0
        assert c["malformed_frames"] > 100 and c["sdo_aborts_sent"] > 100
        assert c["sdo_unknown_command"] > 10 and c["nmt_other_node_ignored"] > 10
