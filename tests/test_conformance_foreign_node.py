"""The conformance suite against a foreign node: a plain `canopen` LocalNode slave whose EDS lists only the
mandatory CiA 301 / CiA 402 objects and a few others. Every optional object or service it lacks is a skip that
names it, never a failure (the checks that it does not pass for its behaviour are failures of the node)."""

from __future__ import annotations

import configparser
import re
import time
from pathlib import Path

import canopen

from virtualaxis.conformance import runner, suite
from virtualaxis.master import DEFAULT_EDS

KEEP = {0x1000, 0x1001, 0x1008, 0x1017, 0x1018, 0x6040, 0x6041, 0x6060, 0x6061, 0x6064, 0x6502}
NODE = 5


def _stripped_eds(path: Path) -> Path:
    """Our EDS with every object but :data:`KEEP` removed (sections and object lists)."""
    cp = configparser.RawConfigParser()
    cp.optionxform = str
    cp.read(DEFAULT_EDS)
    for sec in list(cp.sections()):
        m = re.fullmatch(r"([0-9A-Fa-f]{4})(sub[0-9A-Fa-f]+)?", sec)
        if m and int(m.group(1), 16) not in KEEP:
            cp.remove_section(sec)
    for lst in ("MandatoryObjects", "OptionalObjects", "ManufacturerObjects"):
        if cp.has_section(lst):
            kept = [v for k, v in cp.items(lst) if k != "SupportedObjects" and int(v, 16) in KEEP]
            cp.remove_section(lst)
            cp.add_section(lst)
            cp.set(lst, "SupportedObjects", str(len(kept)))
            for i, v in enumerate(kept, 1):
                cp.set(lst, str(i), v)
    with path.open("w") as fh:
        cp.write(fh)
    return path


def test_missing_optional_objects_and_services_are_skips_with_the_reason(tmp_path):
    eds = str(_stripped_eds(tmp_path / "foreign.eds"))
    channel = f"foreign-{time.perf_counter_ns()}"
    node_net = canopen.Network()
    node_net.connect(interface="virtual", channel=channel, receive_own_messages=False)
    master = canopen.Network()
    master.connect(interface="virtual", channel=channel, receive_own_messages=False)
    try:
        node = canopen.LocalNode(NODE, eds)
        node.sdo[0x6502].raw = 0x80  # CSP only
        node_net.add_node(node)

        def on_nmt(_cob: int, data: bytearray, _t: float) -> None:  # a reset answers with its boot-up
            if len(data) == 2 and data[0] in (0x81, 0x82) and data[1] in (0, NODE):
                node_net.send_message(0x700 + NODE, b"\x00")

        node_net.subscribe(0, on_nmt)
        node.nmt.state = "PRE-OPERATIONAL"
        ctx = runner.Context(master, NODE, eds, sdo_timeout_s=0.3, lockstep=True)
        # a 3-byte EMCY (canopen's own EMCY consumer cannot parse it) is still seen by the suite
        mark = ctx.frames.mark()
        node_net.send_message(0x80 + NODE, b"\x10\x81\x11")
        assert ctx.frames.wait(mark, 0x80 + NODE, None, 1.0) is not None
        checks = suite.select("301-ID,301-SDO-6,301-SDO-11,301-SYNC-1,301-HB-2,301-EMCY-1,402-FE-1,402-HM-1,"
                               "402-PP-3,402-FLD-6,402-FLD-5")
        results = {r.id: r for r in runner.run_checks(ctx, checks)}
    finally:
        master.disconnect()
        node_net.disconnect()
    for r in results.values():
        assert "KeyError" not in r.detail and "was not found" not in r.detail, (r.id, r.detail)
    skipped = {i: r.detail for i, r in results.items() if r.status == "skipped"}
    expect = {"301-SYNC-1": "0x1006", "301-HB-2": "0x1016", "301-EMCY-1": "0x1014", "402-FE-1": "lists no object",
              "402-HM-1": "homing", "402-PP-3": "0x607D", "402-FLD-6": "0x60FD", "301-SDO-6": "block",
              "301-SDO-11": "block"}
    for cid, why in expect.items():
        assert cid in skipped, (cid, results[cid].status, results[cid].detail)
        assert why.lower() in skipped[cid].lower(), (cid, skipped[cid])
    assert results["301-ID-1"].status == "pass"


def _homing_node(tmp_path: Path, supported_modes: int, refused: frozenset[int] = frozenset()):
    """A LocalNode with the stripped EDS plus the homing objects 0x6098 / 0x607C; ``refused``: 0x6098 values the
    node aborts 0x06090030 on write."""
    global KEEP
    keep, KEEP = KEEP, KEEP | {0x6098, 0x607C}
    try:
        eds = str(_stripped_eds(tmp_path / "homing.eds"))
    finally:
        KEEP = keep
    channel = f"foreign-hm-{time.perf_counter_ns()}"
    node_net = canopen.Network()
    node_net.connect(interface="virtual", channel=channel, receive_own_messages=False)
    master = canopen.Network()
    master.connect(interface="virtual", channel=channel, receive_own_messages=False)
    node = canopen.LocalNode(NODE, eds)
    node.sdo[0x6502].raw = supported_modes
    node.sdo[0x6098].raw = 35
    node.sdo[0x607C].raw = 0

    def refuse(index: int, subindex: int, od, data: bytes) -> None:
        if index == 0x6098 and od.decode_raw(data) in refused:
            raise canopen.SdoAbortedError(0x06090030)

    node.add_write_callback(refuse)
    node_net.add_node(node)

    def on_nmt(_cob: int, data: bytearray, _t: float) -> None:
        if len(data) == 2 and data[0] in (0x81, 0x82) and data[1] in (0, NODE):
            node_net.send_message(0x700 + NODE, b"\x00")

    node_net.subscribe(0, on_nmt)
    node.nmt.state = "PRE-OPERATIONAL"
    ctx = runner.Context(master, NODE, eds, sdo_timeout_s=0.3, lockstep=True)
    return node, ctx, (master, node_net)


def test_homing_check_skips_a_node_without_homing_and_leaves_its_homing_objects_alone(tmp_path):
    """0x6502 without the homing bit: 402-HM-1 is a skip naming 0x6502, and it writes neither the homing method
    0x6098 nor the home offset 0x607C of the node (a check skipped for a mode the node lacks changes nothing)."""
    node, ctx, nets = _homing_node(tmp_path, supported_modes=0x80)
    try:
        (res,) = runner.run_checks(ctx, suite.select("402-HM-1"))
    finally:
        for net in nets:
            net.disconnect()
    assert res.status == "skipped" and "0x6502" in res.detail, (res.status, res.detail)
    assert node.sdo[0x6098].raw == 35 and node.sdo[0x607C].raw == 0


def test_homing_check_fails_a_node_refusing_the_method_its_0x6098_holds(tmp_path):
    """0x6502 offers homing and 0x6098 holds method 35, yet writing 35 (and 37) is refused as a value: a failure
    naming 0x6098, not a skip (a node whose only methods are others than 35 / 37 is a skip)."""
    _node, ctx, nets = _homing_node(tmp_path, supported_modes=0xA0, refused=frozenset({35, 37}))
    try:
        (res,) = runner.run_checks(ctx, suite.select("402-HM-1"))
    finally:
        for net in nets:
            net.disconnect()
    assert res.status == "fail" and "0x6098" in res.detail and "35" in res.detail, (res.status, res.detail)
