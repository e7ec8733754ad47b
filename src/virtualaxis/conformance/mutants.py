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

    original_handler = slave_mod.rpdo_handler
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

    slave_mod.rpdo_handler = handler
    slave_mod.CanopenSlave.transmit_sync = transmit_sync


@mutant("rpdo_in_preop", "RPDOs applied in PRE-OPERATIONAL", only="pdo")
def _rpdo_in_preop() -> None:
    from virtualaxis.canopen_slave import slave as slave_mod
    from virtualaxis.canopen_slave.nmt import NMT_STATE

    original_handler = slave_mod.rpdo_handler

    def handler(slave, rpdo):
        handle = original_handler(slave, rpdo)

        def on_frame(msg, now_s):
            if slave.nmt_state == NMT_STATE.PRE_OPERATIONAL:
                slave.pdo.apply(rpdo, bytes(msg.data)[:rpdo.length])
                return
            handle(msg, now_s)

        return on_frame

    slave_mod.rpdo_handler = handler


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


# ---------------------------------------------------------------------------------------- statusword bits
def _statusword_patch(fn: Callable[[object, int], int]) -> None:
    """The statusword the drive publishes, passed through ``fn(drive, sw)``."""
    from virtualaxis.drive.core import Drive

    original = Drive._update_statusword

    def update(self) -> None:
        original(self)
        sw = int(self.objects[(0x6041, 0)])
        new = fn(self, sw)
        if new != sw:
            self._store((0x6041, 0), new)

    Drive._update_statusword = update


@mutant("sw_remote_cleared", "statusword bit 9 (remote) always 0 although the controlword is obeyed", only="sm")
def _sw_remote_cleared() -> None:
    _statusword_patch(lambda _d, sw: sw & ~0x200)


@mutant("sw_target_reached_stuck", "statusword bit 10 (target reached) stuck at 1 in operation enabled",
        only="402-PP-1")
def _sw_target_reached_stuck() -> None:
    _statusword_patch(lambda _d, sw: sw | 0x400 if sw & 0x6F == 0x27 else sw)


@mutant("sw_internal_limit_never", "statusword bit 11 (internal limit active) never set", only="402-PP-3")
def _sw_internal_limit_never() -> None:
    _statusword_patch(lambda _d, sw: sw & ~0x800)


@mutant("sw_quick_stop_bit5_set", "statusword bit 5 (quick stop) set in quick stop active", only="sm")
def _sw_quick_stop_bit5_set() -> None:
    _statusword_patch(lambda _d, sw: sw | 0x20 if sw & 0x6F == 0x07 else sw)


@mutant("sw_setpoint_ack_never", "statusword bit 12 (set-point acknowledge) never set in profile position",
        only="402-PP-1")
def _sw_setpoint_ack_never() -> None:
    _statusword_patch(lambda d, sw: sw & ~0x1000 if int(d.objects[(0x6061, 0)]) == 1 else sw)


# ---------------------------------------------------------------------------------------- state machine
@mutant("sod_enable_operation_direct", "switch on disabled -> operation enabled directly on controlword 0x0F",
        only="sm")
def _sod_enable_operation_direct() -> None:
    from virtualaxis.drive import core
    from virtualaxis.drive.statemachine import Cia402State, Transition

    core._TRANSITIONS[(Cia402State.SWITCH_ON_DISABLED.value, 0xF)] = Transition.T3_4


def _quick_stop_patch(fn) -> None:
    """The stop the drive starts, ``(kind, then)`` passed through ``fn(drive, kind, then)`` in quick stop active."""
    from virtualaxis.drive.core import Drive
    from virtualaxis.drive.statemachine import Cia402State

    original = Drive._start_stop

    def start_stop(self, kind: str, then) -> None:
        if self.cia402_state is Cia402State.QUICK_STOP_ACTIVE:
            kind, then = fn(self, kind, then)
        original(self, kind, then)

    Drive._start_stop = start_stop


@mutant("quick_stop_2_as_1", "quick stop option 0x605A = 2 brakes on the slow-down ramp 0x6084 (option 1)",
        only="402-QS-1")
def _quick_stop_2_as_1() -> None:
    _quick_stop_patch(lambda d, kind, then: ("slow" if int(d.objects[(0x605A, 0)]) == 2 else kind, then))


@mutant("quick_stop_6_as_2", "quick stop options 5..8 end in switch on disabled (as 1..4)", only="sm")
def _quick_stop_6_as_2() -> None:
    from virtualaxis.drive.statemachine import Cia402State

    _quick_stop_patch(lambda _d, kind, then: (kind, Cia402State.SWITCH_ON_DISABLED if then is None else then))


@mutant("halt_ignored", "controlword bit 8 (halt) ignored", only="402-PP-2")
def _halt_ignored() -> None:
    from virtualaxis.drive.core import Drive

    original = Drive._mode_controlword

    def mode_controlword(self, old_cw: int, cw: int) -> None:
        original(self, old_cw & ~0x100, cw & ~0x100)

    Drive._mode_controlword = mode_controlword
    original_cw = Drive._on_controlword

    def on_controlword(self, cw: int) -> None:
        original_cw(self, cw & ~0x100)

    Drive._on_controlword = on_controlword


# ---------------------------------------------------------------------------------------- windows, limits
def _params_patch(**changes) -> None:
    """The drive's monitoring parameters with ``changes`` (whatever the objects say)."""
    import dataclasses

    from virtualaxis.drive.core import Drive

    original = Drive._refresh_params

    def refresh(self) -> None:
        original(self)
        self._pc = dataclasses.replace(self._pc, **changes)

    Drive._refresh_params = refresh


@mutant("following_error_window_ignored", "following error window 0x6065 ignored (no following-error fault)",
        only="402-FE-1")
def _following_error_window_ignored() -> None:
    _params_patch(fe_window_m=float("inf"))


@mutant("position_window_ignored", "position window 0x6067 ignored: target reached within a fixed 2 mm",
        only="402-PP-1")
def _position_window_ignored() -> None:
    _params_patch(position_window_m=2e-3)


@mutant("software_limit_ignored", "software position limits 0x607D ignored", only="402-PP-3")
def _software_limit_ignored() -> None:
    _params_patch(travel_limits_m=None)


@mutant("loss_of_control_ignored", "abort connection option 0x6007 ignored on NMT stop / reset communication",
        only="loss")
def _loss_of_control_ignored() -> None:
    from virtualaxis.drive.core import Drive

    original = Drive.communication_error

    def communication_error(self, kind: str, detail: int = 0) -> None:
        if not kind.startswith("nmt_"):
            original(self, kind, detail)

    Drive.communication_error = communication_error


# ---------------------------------------------------------------------------------------- errors, EMCY
@mutant("error_register_not_kept", "0x1001 reads without bit 0 (generic error) while a fault is present (the EMCY "
        "frame carries the bit)", only="402-FE-1")
def _error_register_not_kept() -> None:
    _upload_patch({0x1001: lambda v: v & ~0x01})


@mutant("error_history_not_updated", "pre-defined error field 0x1003 not updated on an error", only="402-FE-1")
def _error_history_not_updated() -> None:
    from virtualaxis.canopen_slave.emcy import EmcyProducer

    EmcyProducer.push_history = lambda self, code, info=0: None


@mutant("error_code_not_set", "error code 0x603F reads 0 while a fault is present", only="402-FE-1")
def _error_code_not_set() -> None:
    _upload_patch({0x603F: lambda v: 0})


@mutant("fault_reset_silent", "no EMCY 0x0000 (error reset) after a fault reset", only="402-FE-1")
def _fault_reset_silent() -> None:
    from virtualaxis.canopen_slave.emcy import EmcyProducer

    original = EmcyProducer.produce

    def produce(self, code: int, register: int, data: bytes, now_s: float) -> None:
        if code:
            original(self, code, register, data, now_s)

    EmcyProducer.produce = produce


@mutant("emcy_cob_id_without_node_id", "0x1014 (COB-ID EMCY) reads 0x80, not 0x80 + node id", only="301-EMCY-1")
def _emcy_cob_id_without_node_id() -> None:
    _upload_patch({0x1014: lambda v: v & ~0x7F})


def _upload_patch(rules: dict) -> None:
    """SDO uploads of the objects in ``rules`` (integers) answer ``rule(value)`` instead of the value."""
    from virtualaxis.canopen_slave.slave import CanopenSlave

    original = CanopenSlave.sdo_upload

    def sdo_upload(self, index: int, sub: int) -> bytes:
        data = original(self, index, sub)
        if index in rules and 1 <= len(data) <= 4:
            mask = (1 << (8 * len(data))) - 1
            return (rules[index](int.from_bytes(data, "little")) & mask).to_bytes(len(data), "little")
        return data

    CanopenSlave.sdo_upload = sdo_upload


@mutant("device_type_not_402", "0x1000 device type reads profile 0x0191, not 0x0192 (CiA 402)", only="301-ID-1")
def _device_type_not_402() -> None:
    _upload_patch({0x1000: lambda v: (v & ~0xFFFF) | 0x0191})


# ---------------------------------------------------------------------------------------- SDO abort codes
def _abort_swap(swap: dict[int, int]) -> None:
    """Every SDO abort with a code in ``swap`` is sent with the code it maps to."""
    from virtualaxis.canopen_slave.sdo_server import SdoServer

    original = SdoServer.abort

    def abort(self, code: int, index: int | None = None, sub: int | None = None) -> None:
        original(self, swap.get(code, code), index, sub)

    SdoServer.abort = abort


@mutant("sdo_no_subindex_as_no_object", "a missing sub-index aborted 0x06020000 instead of 0x06090011",
        only="sdo")
def _sdo_no_subindex_as_no_object() -> None:
    _abort_swap({0x06090011: 0x06020000})


@mutant("sdo_read_only_wrong_abort", "a write to a read-only object aborted 0x06010000 instead of 0x06010002",
        only="sdo")
def _sdo_read_only_wrong_abort() -> None:
    _abort_swap({0x06010002: 0x06010000})


@mutant("sdo_write_only_wrong_abort", "a read of a write-only object aborted 0x06010000 instead of 0x06010001",
        only="sdo")
def _sdo_write_only_wrong_abort() -> None:
    _abort_swap({0x06010001: 0x06010000})


@mutant("sdo_length_wrong_abort", "a write of the wrong length aborted 0x08000000 instead of 0x0607001x",
        only="sdo")
def _sdo_length_wrong_abort() -> None:
    _abort_swap({0x06070010: 0x08000000, 0x06070012: 0x08000000, 0x06070013: 0x08000000})


@mutant("sdo_command_wrong_abort", "an unknown SDO command specifier aborted 0x08000000 instead of 0x05040001",
        only="sdo")
def _sdo_command_wrong_abort() -> None:
    _abort_swap({0x05040001: 0x08000000})


@mutant("sdo_toggle_wrong_abort", "a segment with the wrong toggle bit aborted 0x08000000 instead of 0x05030000",
        only="sdo")
def _sdo_toggle_wrong_abort() -> None:
    _abort_swap({0x05030000: 0x08000000})


@mutant("sdo_value_limits_ignored", "values beyond an object's HighLimit / LowLimit accepted", only="sdo")
def _sdo_value_limits_ignored() -> None:
    from virtualaxis.canopen_slave.slave import CanopenSlave
    from virtualaxis.drive.core import Drive
    from virtualaxis.drive.object_table import ObjectAccessError

    CanopenSlave._check_limits = staticmethod(lambda entry, value: None)
    original = Drive.check_object_write

    def check_object_write(self, index: int, sub: int, value) -> None:
        try:
            original(self, index, sub, value)
        except ObjectAccessError as exc:
            if exc.code not in (0x06090031, 0x06090032):
                raise

    Drive.check_object_write = check_object_write


@mutant("mode_unsupported_accepted", "0x6060 accepts a mode 0x6502 does not list (0x6061 shows it)", only="sdo")
def _mode_unsupported_accepted() -> None:
    from virtualaxis.drive.core import Drive

    original_check = Drive.check_object_write
    original_mode = Drive._on_mode

    def check_object_write(self, index: int, sub: int, value) -> None:
        if index == 0x6060:
            return
        original_check(self, index, sub, value)

    def on_mode(self, mode: int) -> None:
        from virtualaxis.drive.opmodes import SUPPORTED_MODE_BITS

        if mode not in SUPPORTED_MODE_BITS or not SUPPORTED_MODE_BITS[mode] & int(self.objects[(0x6502, 0)]):
            self._store((0x6061, 0), mode)
            return
        original_mode(self, mode)

    Drive.check_object_write = check_object_write
    Drive._on_mode = on_mode


@mutant("homing_method_refused", "0x6098 refuses the homing methods on the current position (35, 37) it runs",
        only="402-HM-1")
def _homing_method_refused() -> None:
    from virtualaxis.drive.core import Drive
    from virtualaxis.drive.object_table import ObjectAccessError

    original = Drive.check_object_write

    def check_object_write(self, index: int, sub: int, value) -> None:
        if index == 0x6098 and value in (35, 37):
            raise ObjectAccessError(0x06090030, f"homing method {value} refused")
        original(self, index, sub, value)

    Drive.check_object_write = check_object_write


# ---------------------------------------------------------------------------------------- PDO mapping, NMT
@mutant("pdo_maps_non_mappable", "an object the EDS marks not PDO-mappable is accepted in a mapping", only="pdo")
def _pdo_maps_non_mappable() -> None:
    from virtualaxis.canopen_slave import errors
    from virtualaxis.canopen_slave.pdo import PdoEngine

    original = PdoEngine.check_mapping

    def check_mapping(self, mapping: int, receive: bool):
        try:
            return original(self, mapping, receive)
        except errors.SdoAbort as exc:
            entry = self.slave.od.entries.get((mapping >> 16, (mapping >> 8) & 0xFF))
            if exc.code == errors.NOT_MAPPABLE and entry is not None and entry.fmt is not None:
                return entry
            raise

    PdoEngine.check_mapping = check_mapping


@mutant("pdo_mapping_too_long_wrong_abort", "a mapping longer than 64 bits aborted 0x06040043, not 0x06040042",
        only="pdo")
def _pdo_mapping_too_long_wrong_abort() -> None:
    _abort_swap({0x06040042: 0x06040043})


@mutant("tpdo_in_preop", "synchronous TPDOs sent in PRE-OPERATIONAL", only="pdo")
def _tpdo_in_preop() -> None:
    from virtualaxis.canopen_slave import slave as slave_mod
    from virtualaxis.canopen_slave.nmt import NMT_STATE

    original_transmit = slave_mod.CanopenSlave.transmit_sync

    def transmit_sync(self, counter, now_s):
        if self.nmt_state == NMT_STATE.PRE_OPERATIONAL:
            self.pdo.on_sync(counter, self.sync.counter_enabled, now_s)
            return
        original_transmit(self, counter, now_s)

    slave_mod.CanopenSlave.transmit_sync = transmit_sync


@mutant("reset_communication_keeps_pdo_parameters", "NMT reset communication leaves the PDO COB-IDs, types "
        "and mappings (0x1400-0x1BFF) as written", only="301-NMT-3")
def _reset_communication_keeps_pdo_parameters() -> None:
    from virtualaxis.canopen_slave.slave import CanopenSlave

    original = CanopenSlave._power_on_values

    def power_on_values(self, lo: int, hi: int, keep: frozenset[int] = frozenset()) -> None:
        if (lo, hi) == (0x1000, 0x1FFF):
            original(self, 0x1000, 0x13FF, keep)
            original(self, 0x1C00, 0x1FFF, keep)
            return
        original(self, lo, hi, keep)

    CanopenSlave._power_on_values = power_on_values


@mutant("sdo_answered_in_stopped", "SDO requests answered in NMT STOPPED", only="nmt")
def _sdo_answered_in_stopped() -> None:
    from virtualaxis.canopen_slave.slave import CanopenSlave

    def on_sdo(self, msg, now_s: float) -> None:
        if not msg.is_remote_frame:
            self.sdo.on_frame(bytes(msg.data), now_s)

    CanopenSlave._on_sdo = on_sdo


@mutant("guard_toggle_stuck", "node guarding answers without alternating the toggle bit", only="nmt")
def _guard_toggle_stuck() -> None:
    from virtualaxis.canopen_slave.heartbeat import NodeGuarding

    original = NodeGuarding.on_rtr

    def on_rtr(self, now_s: float) -> None:
        original(self, now_s)
        self.toggle = 0

    NodeGuarding.on_rtr = on_rtr


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
