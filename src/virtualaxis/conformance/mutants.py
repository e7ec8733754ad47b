"""Planted defects: our drive served with one behaviour the conformance suite claims to check broken.

Each mutant is a small patch of one behaviour, applied in the serving process only:

    python -m virtualaxis.conformance.mutants heartbeat_slow serve --can udp_multicast:... --lockstep

(the arguments after the mutant's name are those of ``virtualaxis``). ``benchmarks/bench_conformance_mutants.py``
serves each mutant and runs the suite against it: a mutant is *killed* when some check fails, and the
benchmark names the check. ``python -m virtualaxis.conformance.mutants --list`` lists them.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class Mutant:
    name: str
    behaviour: str  # what is broken
    pacing: str  # "lockstep" or "realtime": how the benchmark serves it (realtime: what only real time shows)
    only: str  # the checks (ids, prefixes, families) the benchmark runs against it ("" = the whole suite)
    apply: Callable[[], None]


MUTANTS: dict[str, Mutant] = {}


def mutant(name: str, behaviour: str, *, pacing: str = "lockstep", only: str = ""):
    def deco(fn: Callable[[], None]) -> Callable[[], None]:
        MUTANTS[name] = Mutant(name, behaviour, pacing, only, fn)
        return fn

    return deco


# ---------------------------------------------------------------------------------------- CiA 402 drive
@mutant("fault_reset_level", "fault reset on the level of controlword bit 7, not its rising edge", only="reaction")
def _fault_reset_level() -> None:
    from virtualaxis.drive.core import Drive

    original = Drive._on_controlword

    def on_controlword(self, cw: int) -> None:
        if cw & 0x80 and self.cia402_state.name == "FAULT":
            self._cw = cw & ~0x80  # (the edge detector sees a rising edge on every write with bit 7)
        original(self, cw)

    Drive._on_controlword = on_controlword


@mutant("fault_reaction_ignores_605e", "0x605E ignored: every fault reaction is the quick-stop ramp",
        only="reaction")
def _fault_reaction_ignores_605e() -> None:
    from virtualaxis.drive import reactions

    original = reactions.fault_reaction_kind
    reactions.fault_reaction_kind = lambda reaction_class, _option: original(reaction_class, 2)


@mutant("mode_echo_only", "0x6061 echoes 0x6060 but the drive stays in the mode it was in", only="402-MODE-1")
def _mode_echo_only() -> None:
    from virtualaxis.drive.core import Drive

    def on_mode(self, mode: int) -> None:
        self._store((0x6061, 0), mode)
        self._update_statusword()

    Drive._on_mode = on_mode


@mutant("csp_target_late", "each CSP / CSV / CST target applied one SYNC late", only="modes")
def _csp_target_late() -> None:
    from virtualaxis.drive.core import Drive

    original = Drive._react
    held: dict = {}

    def react(self, key, value) -> None:
        if key in ((0x607A, 0), (0x60FF, 0), (0x6071, 0)) and self._mode in (8, 9, 10):
            value, held[key] = held.get(key, value), value
        original(self, key, value)

    Drive._react = react


@mutant("limit_switch_ignored", "hardware limit switches never seen (0x60FD and the stop)", only="limits")
def _limit_switch_ignored() -> None:
    from virtualaxis.drive.core import Drive

    original = Drive._switches

    def switches(self, x_plant_m: float, method: int | None = None):
        _neg, _pos, home = original(self, x_plant_m, method)
        return False, False, home

    Drive._switches = switches


# ---------------------------------------------------------------------------------------- CiA 301 slave
@mutant("heartbeat_slow", "heartbeat producer 1.25 x slower than 0x1017", only="nmt")
def _heartbeat_slow() -> None:
    from virtualaxis.canopen_slave.heartbeat import HeartbeatProducer

    HeartbeatProducer.period_s = property(lambda self: self.slave.od.value(0x1017) * 1.25e-3)


@mutant("pdo_in_stopped", "PDOs sent and applied in NMT STOPPED", only="pdo,loss")
def _pdo_in_stopped() -> None:
    from virtualaxis.canopen_slave import slave as slave_mod
    from virtualaxis.canopen_slave.nmt import NMT_STATE

    original_handler = slave_mod._rpdo_handler
    original_transmit = slave_mod.CanopenSlave.transmit_sync

    def handler(slave, rpdo):
        handle = original_handler(slave, rpdo)

        def on_frame(msg, now_s):
            if slave.nmt_state == NMT_STATE.STOPPED:
                slave.pdo.apply(rpdo, bytes(msg.data)[:rpdo.length])
                return
            handle(msg, now_s)

        return on_frame

    def transmit_sync(self, counter, now_s):
        if self.nmt_state == NMT_STATE.STOPPED:
            self.pdo.on_sync(counter, self.sync.counter_enabled, now_s)
            return
        original_transmit(self, counter, now_s)

    slave_mod._rpdo_handler = handler
    slave_mod.CanopenSlave.transmit_sync = transmit_sync


@mutant("rpdo_in_preop", "RPDOs applied in PRE-OPERATIONAL", only="pdo")
def _rpdo_in_preop() -> None:
    from virtualaxis.canopen_slave import slave as slave_mod
    from virtualaxis.canopen_slave.nmt import NMT_STATE

    original_handler = slave_mod._rpdo_handler

    def handler(slave, rpdo):
        handle = original_handler(slave, rpdo)

        def on_frame(msg, now_s):
            if slave.nmt_state == NMT_STATE.PRE_OPERATIONAL:
                slave.pdo.apply(rpdo, bytes(msg.data)[:rpdo.length])
                return
            handle(msg, now_s)

        return on_frame

    slave_mod._rpdo_handler = handler


@mutant("sync_timeout_silent", "no EMCY 0x8100 when SYNC stops", pacing="realtime", only="sync")
def _sync_timeout_silent() -> None:
    from virtualaxis.canopen_slave.slave import CanopenSlave

    CanopenSlave._sync_timeout = lambda self: None


@mutant("heartbeat_consumer_silent", "heartbeat consumer 0x1016 never reports a lost node (no EMCY 0x8130)",
        only="301-HB-2")
def _heartbeat_consumer_silent() -> None:
    from virtualaxis.canopen_slave.heartbeat import HeartbeatConsumer

    HeartbeatConsumer.poll = lambda self, now_s: None


@mutant("sdo_unknown_object_wrong_abort", "an unknown object aborted with 0x08000000 instead of 0x06020000",
        only="sdo,eds")
def _sdo_wrong_abort() -> None:
    from virtualaxis.canopen_slave import errors
    from virtualaxis.canopen_slave.slave import CanopenSlave

    original = CanopenSlave._lookup

    def lookup(self, index: int, sub: int):
        try:
            return original(self, index, sub)
        except errors.SdoAbort as exc:
            if exc.code == errors.NO_OBJECT:
                raise errors.SdoAbort(errors.GENERAL_ERROR, "unknown") from None
            raise

    CanopenSlave._lookup = lookup


@mutant("event_timer_slow", "TPDO event timer (0x18xx:5) runs 1.5 x slower than configured", only="301-PDO-7")
def _event_timer_slow() -> None:
    from virtualaxis.canopen_slave.pdo import PdoEngine, Tpdo

    original = PdoEngine._configure

    def configure(self, pdo) -> None:
        original(self, pdo)
        if isinstance(pdo, Tpdo):
            pdo.event_s *= 1.5

    PdoEngine._configure = configure


@mutant("tpdo_every_sync", "a cyclic TPDO (transmission type 2..240) sent on every SYNC", only="301-PDO-6")
def _tpdo_every_sync() -> None:
    from virtualaxis.canopen_slave.pdo import PdoEngine

    PdoEngine._cyclic_due = staticmethod(lambda tpdo, counter, counter_enabled: True)


@mutant("sync_rpdo_at_once", "a synchronous RPDO applied when it arrives, not at the next SYNC", only="301-PDO-8")
def _sync_rpdo_at_once() -> None:
    from virtualaxis.canopen_slave.pdo import PdoEngine

    original = PdoEngine.on_rpdo

    def on_rpdo(self, rpdo, data: bytes, now_s: float) -> None:
        original(self, rpdo, data, now_s)
        if rpdo.pending is not None:
            pending, rpdo.pending = rpdo.pending, None
            self.apply(rpdo, pending)

    PdoEngine.on_rpdo = on_rpdo


@mutant("homing_offset_ignored", "homing on the current position sets 0x6064 to 0, not to the home offset 0x607C",
        only="402-HM-1")
def _homing_offset_ignored() -> None:
    from virtualaxis.drive.mode_context import ModeContext

    ModeContext.home_offset_m = lambda self: 0.0  # (0x607C read as 0 when the home point is set)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "--list"):
        for m in MUTANTS.values():
            print(f"{m.name:<32} {m.pacing:<9} {m.only or 'all':<12} {m.behaviour}")
        return 0
    name, rest = argv[0], argv[1:]
    if name not in MUTANTS:
        print(f"error: no mutant {name!r} (--list shows them)", file=sys.stderr)
        return 2
    MUTANTS[name].apply()
    from virtualaxis.cli.main import main as cli_main

    return cli_main(rest)


if __name__ == "__main__":
    sys.exit(main())
