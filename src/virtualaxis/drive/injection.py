"""Fault injection for HIL rigs and controller CI: faults a real drive meets in the field, on demand.

Built on the drive's fault-injection contract (docs/drive-api.md): cycle hooks, ``raise_fault`` with a
persistent cause, ``clear_cause``, ``set_warning`` and the plant (``simulator``). Each fault acts where it
acts on a real machine, so that the drive's own monitors, reactions and the CiA 301 stack respond:

============================  ========  ===================================================================
kind                          EMCY      how it is produced / how it clears
============================  ========  ===================================================================
``encoder_loss``              0x7305    position sensor signal lost: OFF2 (coast); reset refused until cleared
``over_current``              0x2310    power-unit over-current trip: OFF2; a reset succeeds, but the power
                                        stage trips again whenever it is enabled while the cause is there
``motor_overtemperature``     0x4310    extra winding losses while the power stage is on: the drive's thermal
                                        model rises, warning A07910 (statusword bit 7, 0x2031) at 0x200A,
                                        fault 0x4310 at 0x200B; reset refused until the winding is below it
``dc_link_undervoltage``      0x3220    supply lost: 0x605E reaction; reset refused until cleared
``dc_link_overvoltage``       0x3210    regenerated energy not dissipated: 0x605E; refused until cleared
``following_error``           0x8611    a holding brake on the table (slips beyond ``magnitude`` N, default
                                        60 kN): the drive's following-error monitor trips; clears when the
                                        brake is released
``limit_switch``              0xFF11/10 the hardware limit switch input (``magnitude`` > 0: plus, < 0: minus,
                                        0: the direction of motion) reads active: the drive's limit-switch
                                        monitor reacts (OFF3, fault or warning per 0x2013), motion only away
``lost_rpdos``                (0x8250)  RPDO frames never reach the drive: the RPDO event timer (0x1400+n:5)
                                        or the control loop decide (0x6007)
``heartbeat_loss``            (0x8130)  the master's heartbeat never reaches the drive: consumer heartbeat
                                        0x1016 expires (EMCY 0x8130, 0x1029 / 0x6007 reaction)
``bus_off``                   0x8140    the CAN controller is bus-off: nothing sent or received for
                                        ``magnitude`` ms (default 500), then it recovers by itself as a CAN
                                        controller does (a bus-off node hears no request to clear it): EMCY
                                        0x8140 and the 0x6007 reaction; also on clear and after each off phase
                                        of the intermittent variant
``safe_torque_off``           0x5400    the STO input drops: torque off at once, the brake closes, SWITCH ON
                                        DISABLED, warning EMCY; on clear the restart interlock holds the drive
                                        disabled until shutdown -> switch on -> enable operation
============================  ========  ===================================================================

Intermittent variant of each: ``duty`` in (0, 1) and ``period_s``: active for ``duty * period_s`` of every
period (drive time), e.g. a loose encoder connector.

Channels: this Python API (:class:`FaultInjector`), CANopen objects 0x5FF0..0x5FF6 (:class:`InjectionApp`,
refused with abort 0x08000022 unless the drive was served with ``--allow-fault-injection``), the CLI
``virtualaxis fault``; the Modbus registers 40600..40609 and the MQTT topic ``<axis>/fault/set`` of
``virtualaxis serve`` (:mod:`virtualaxis.services`) go through :func:`FaultInjector.command` (a kind name or
number plus options, the same refusal rules).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from virtualaxis.canopen_slave.app import CanopenApplication

#: kind name -> number used on the CANopen channel (0x5FF0 / 0x5FF1)
KINDS: dict[str, int] = {
    "encoder_loss": 1,
    "over_current": 2,
    "motor_overtemperature": 3,
    "dc_link_undervoltage": 4,
    "dc_link_overvoltage": 5,
    "following_error": 6,
    "limit_switch": 7,
    "lost_rpdos": 8,
    "heartbeat_loss": 9,
    "bus_off": 10,
    "safe_torque_off": 11,
}
KIND_NAMES = {v: k for k, v in KINDS.items()}
#: kinds whose cause persists in the drive (a fault reset is refused while it lasts, a power-on reset finds it again)
PERSISTENT_KINDS = frozenset({"encoder_loss", "dc_link_undervoltage", "dc_link_overvoltage"})

#: EMCY code a master sees for each kind (the one raised directly or by the drive's monitor / stack)
EMCY_OF_KIND: dict[str, int] = {
    "encoder_loss": 0x7305,
    "over_current": 0x2310,
    "motor_overtemperature": 0x4310,
    "dc_link_undervoltage": 0x3220,
    "dc_link_overvoltage": 0x3210,
    "following_error": 0x8611,
    "limit_switch": 0xFF11,
    "lost_rpdos": 0x8250,
    "heartbeat_loss": 0x8130,
    "bus_off": 0x8140,
    "safe_torque_off": 0x5400,
}

#: CANopen objects of the channel (manufacturer-specific area; listed in eds/virtualaxis.eds)
OBJ_INJECT = 0x5FF0  # u8 w: inject kind number (with 0x5FF2..0x5FF4 as options); read: last injected
OBJ_CLEAR = 0x5FF1  # u8 w: clear kind number (0xFF: all)
OBJ_DUTY = 0x5FF2  # u16: duty cycle of the next injection [per mille], 0 or 1000 = permanent
OBJ_PERIOD = 0x5FF3  # u32: period of the intermittent variant [ms]
OBJ_MAGNITUDE = 0x5FF4  # i32: kind-specific magnitude (brake force [N], limit switch side, heating [K/s])
OBJ_ACTIVE = 0x5FF5  # u32 ro: bit (kind number - 1) set while a kind is injected
OBJ_ALLOWED = 0x5FF6  # u8 ro: 1 when the drive accepts injection
OBJ_LEGACY_INJECT = 0x2010  # the drive's own injection object (EMCY code), gated like the channel
CHANNEL_OBJECTS = range(OBJ_INJECT, OBJ_ALLOWED + 1)

ABORT_DEVICE_STATE = 0x08000022
ABORT_VALUE_INVALID = 0x06090030

DEFAULT_BRAKE_FORCE_N = 60_000.0
DEFAULT_HEATING_K_S = 60.0
DEFAULT_BUS_OFF_MS = 500.0  # a bus-off over CAN must end by itself: the node hears no request to clear it


class InjectionRefused(Exception):
    """An injection request is refused; ``code`` is the SDO abort code a CANopen master gets."""

    def __init__(self, code: int, message: str):
        super().__init__(message)
        self.code = code


@dataclass
class Injection:
    """One active injected fault."""

    kind: str
    duty: float = 1.0  # fraction of each period the fault is present (1: permanent)
    period_s: float = 1.0
    magnitude: float = 0.0
    started_s: float = 0.0  # drive time at injection
    present: bool = False  # the cause is present in this cycle
    side: int = 0  # limit switch: +1 plus, -1 minus
    anchor_m: float | None = None  # following error: table position where the brake holds [m]

    def present_at(self, t_s: float) -> bool:
        if self.duty >= 1.0:
            return True
        phase = ((t_s - self.started_s) % self.period_s) / self.period_s
        return phase < self.duty


class FaultInjector:
    """Faults on demand for one :class:`~virtualaxis.drive.Drive` (and its CANopen slave, if served).

    ``inject(kind, duty=1.0, period_s=1.0, magnitude=None)`` / ``clear(kind=None)``; ``active`` lists the
    injected kinds. Thread-safe (takes the drive's lock)."""

    def __init__(self, drive: Any, slave: Any = None, *, allowed: bool = True):
        self.drive = drive
        self.slave = slave
        self.allowed = allowed
        self._active: dict[str, Injection] = {}
        self._cycles = 0
        self._lock = threading.RLock()
        self._drop_rpdo = False
        self._drop_heartbeat = False
        self._bus_off = False
        self._switch_force = 0  # +1 / -1: limit switch input forced active
        self._switch_hooked = False  # self._switches is the drive's switch input
        drive.add_cycle_hook(self._cycle)
        if slave is not None:
            self.attach_slave(slave)

    # ------------------------------------------------------------------ public API
    @property
    def active(self) -> dict[str, Injection]:
        with self._lock:
            return dict(self._active)

    @property
    def active_bits(self) -> int:
        """Bit (kind number - 1) set for each active kind (0x5FF5, Modbus 40607)."""
        bits = 0
        for kind in self.active:
            bits |= 1 << (KINDS[kind] - 1)
        return bits

    def now_s(self) -> float:
        """Drive time [s] as counted by the injector's cycle hook."""
        return self._cycles * self.drive.cycle_s

    def inject(self, kind: str, *, duty: float = 1.0, period_s: float = 1.0, magnitude: float | None = None) -> None:
        """Inject ``kind`` (see :data:`KINDS`); ``duty`` < 1 makes it intermittent with ``period_s`` [s] (a permanent
        fault, ``duty`` 1, has no period: ``period_s`` is not used, 0 included)."""
        if not self.allowed:
            raise InjectionRefused(ABORT_DEVICE_STATE, "fault injection is off (serve with --allow-fault-injection)")
        if kind not in KINDS:
            raise InjectionRefused(ABORT_VALUE_INVALID, f"unknown fault kind {kind!r} (known: {', '.join(KINDS)})")
        if not (isinstance(duty, (int, float)) and 0.0 < duty <= 1.0):
            raise InjectionRefused(ABORT_VALUE_INVALID, f"duty must be in (0, 1] (got {duty!r})")
        if duty == 1.0:
            period_s = 1.0  # (permanent: not used)
        elif not (isinstance(period_s, (int, float)) and math.isfinite(period_s) and 0.002 <= period_s <= 3600):
            raise InjectionRefused(ABORT_VALUE_INVALID, f"period_s must be 0.002..3600 s for an intermittent fault "
                                                        f"(got {period_s!r})")
        if magnitude is not None and not math.isfinite(magnitude):
            raise InjectionRefused(ABORT_VALUE_INVALID, "magnitude must be finite")
        with self.drive.lock, self._lock:
            self._release(kind)
            inj = Injection(kind, float(duty), float(period_s), float(magnitude or 0.0), self.now_s())
            if kind == "limit_switch":
                inj.side = 1 if inj.magnitude > 0 else -1 if inj.magnitude < 0 else 0
                if inj.side == 0:
                    v = self.drive.simulator.state.velocity_m_s
                    inj.side = -1 if v < 0 else 1
            self._active[kind] = inj
            if kind != "bus_off":  # bus-off from the next cycle: the master gets the confirmation of its request
                self._apply(inj, inj.present_at(self.now_s()))

    def clear(self, kind: str | None = None) -> None:
        """Remove an injected fault (all with ``None``): its cause goes; the fault (if any) stays until the
        master resets it, as on a real drive."""
        if kind is not None and kind not in KINDS:
            raise InjectionRefused(ABORT_VALUE_INVALID, f"unknown fault kind {kind!r} (known: {', '.join(KINDS)})")
        with self.drive.lock, self._lock:
            for k in [kind] if kind else list(self._active):
                self._release(k)

    def command(self, action: str, kind: str | int | None = None, **options: Any) -> None:
        """One entry point for side channels (Modbus, MQTT): ``action`` "inject" / "clear", ``kind`` a name or
        number of :data:`KINDS`; options as :meth:`inject`. Refusals raise :class:`InjectionRefused`; without
        ``allowed`` every command is refused 0x08000022 first, whatever its kind or action."""
        if not self.allowed:
            raise InjectionRefused(ABORT_DEVICE_STATE, "fault injection is off (serve --allow-fault-injection)")
        if isinstance(kind, int) and not isinstance(kind, bool):
            if kind not in KIND_NAMES:
                raise InjectionRefused(ABORT_VALUE_INVALID, f"unknown fault kind number {kind}")
            kind = KIND_NAMES[kind]
        if action == "inject":
            if kind is None:
                raise InjectionRefused(ABORT_VALUE_INVALID, "inject needs a fault kind")
            self.inject(kind, **options)
        elif action == "clear":
            if not self.allowed:
                raise InjectionRefused(ABORT_DEVICE_STATE, "fault injection is off")
            self.clear(kind)
        else:
            raise InjectionRefused(ABORT_VALUE_INVALID, f"unknown action {action!r} (inject, clear)")

    def close(self) -> None:
        """Remove every injection and the cycle hook."""
        self.clear()
        self.drive.remove_cycle_hook(self._cycle)

    # ------------------------------------------------------------------ per cycle
    def _cycle(self, drive: Any) -> None:
        self._cycles += 1
        if not self._active:
            return
        t = self.now_s()
        for inj in list(self._active.values()):
            if inj.kind == "bus_off" and inj.duty >= 1.0 and t - inj.started_s >= self._bus_off_s(inj):
                self._release("bus_off")  # the CAN controller's automatic recovery (128 x 11 recessive bits)
                continue
            present = inj.present_at(t)
            if present != inj.present:
                self._apply(inj, present)
            if present:
                self._continuous(inj)

    def _continuous(self, inj: Injection) -> None:
        drive = self.drive
        if inj.kind in PERSISTENT_KINDS:  # the cause outlives a power-on reset (NMT reset node): faults again
            self._raise_persistent(inj.kind)
        elif inj.kind == "following_error":
            sim = drive.simulator
            base = float(drive.read_object(0x2011, 0))
            sim.set_external_force(base + self._brake_force(inj))
        elif inj.kind == "over_current":  # the cause is still there: the power stage trips again when enabled
            if getattr(drive.cia402_state, "name", "") == "OPERATION_ENABLED":
                drive.raise_fault(EMCY_OF_KIND["over_current"], 0)
        elif inj.kind == "motor_overtemperature":
            if getattr(drive.cia402_state, "name", "") == "OPERATION_ENABLED" and hasattr(drive, "add_motor_heat"):
                drive.add_motor_heat((inj.magnitude or DEFAULT_HEATING_K_S) * drive.cycle_s)

    def _brake_force(self, inj: Injection) -> float:
        """A holding brake clamping the table [N]: a stiff spring-damper anchored where the table was when it
        closed, slipping (the anchor follows) beyond ``magnitude`` N (default :data:`DEFAULT_BRAKE_FORCE_N`).
        Stiffness and damping keep the once-per-cycle force update stable (k dt^2 / m = 0.1, c dt / m = 0.3 with
        the table mass m): a Coulomb force switched by the sign of the speed chatters at the cycle rate instead
        (60 kN on 300 kg changes the speed by 0.2 m/s per 1 ms cycle) and never stops the table."""
        drive = self.drive
        st = drive.simulator.state
        x, v = st.table_position_m, st.velocity_m_s
        if inj.anchor_m is None:
            inj.anchor_m = x
        f_max = abs(inj.magnitude) or DEFAULT_BRAKE_FORCE_N
        mass, dt = float(drive.cfg.mechanics.table_mass_kg), drive.cycle_s
        k, c = 0.1 * mass / dt**2, 0.3 * mass / dt
        f = -k * (x - inj.anchor_m) - c * v
        if abs(f) > f_max:  # slipping: the anchor follows to where the spring holds f_max
            f = math.copysign(f_max, f)
            inj.anchor_m = x + (f + c * v) / k
        return f

    def _apply(self, inj: Injection, present: bool) -> None:
        """The cause appears (``present``) or goes."""
        inj.present = present
        drive, kind = self.drive, inj.kind
        code = EMCY_OF_KIND[kind]
        if kind in PERSISTENT_KINDS:
            if present:
                self._raise_persistent(kind)
            else:
                drive.clear_cause(f"injected {kind}")
        elif kind == "over_current":
            if present and getattr(drive.cia402_state, "name", "") not in ("FAULT", "FAULT_REACTION_ACTIVE"):
                drive.raise_fault(code, 0)
        elif kind == "following_error":
            if not present:
                drive.simulator.set_external_force(float(drive.read_object(0x2011, 0)))
                inj.anchor_m = None
        elif kind == "limit_switch":
            self._force_switch(inj.side if present else 0)
        elif kind == "safe_torque_off":
            drive.set_safe_torque_off("injected", present)
        elif kind == "lost_rpdos":
            self._drop_rpdo = present
        elif kind == "heartbeat_loss":
            self._drop_heartbeat = present
            if present and self.slave is None:  # not served: no consumer to expire; the reaction directly
                drive.communication_error("heartbeat_lost", 0)
        elif kind == "bus_off":
            was = self._bus_off
            self._bus_off = present
            if was and not present:
                self._recover_from_bus_off()
            elif present and self.slave is None:
                drive.communication_error("bus_off", 0)

    def _raise_persistent(self, kind: str) -> None:
        """The fault of a persistent kind with its cause, unless the drive holds that cause already."""
        code = EMCY_OF_KIND[kind]
        if code not in self.drive.causes:
            self.drive.raise_fault(code, 0, cause=f"injected {kind}")

    def _release(self, kind: str) -> None:
        inj = self._active.pop(kind, None)
        if inj is not None and inj.present:
            self._apply(inj, False)

    @staticmethod
    def _bus_off_s(inj: Injection) -> float:
        """How long one (permanent-variant) bus-off lasts before the controller recovers by itself [s]:
        ``magnitude`` ms, default :data:`DEFAULT_BUS_OFF_MS`."""
        return (inj.magnitude or DEFAULT_BUS_OFF_MS) / 1000.0

    def _recover_from_bus_off(self) -> None:
        """Back on the bus: EMCY 0x8140 (recovered from bus off), then the 0x6007 reaction."""
        if self.slave is not None:
            self.slave.emcy(0x8140, 0x10, b"", communication=True)
        self.drive.communication_error("bus_off", 0)

    def _force_switch(self, side: int) -> None:
        """Force the limit switch input (:meth:`Drive.set_switch_input`) active on ``side`` (0: as the plant is)."""
        drive = self.drive
        self._switch_force = side
        if not self._switch_hooked and hasattr(drive, "set_switch_input"):
            drive.set_switch_input(self._switches)
            self._switch_hooked = True
        if not self._switch_hooked and side:  # a drive without a switch input: the fault directly
            drive.raise_fault(0xFF11 if side > 0 else 0xFF10, 0)

    def _switches(self, neg: bool, pos: bool, home: bool) -> tuple[bool, bool, bool]:
        f = self._switch_force
        return neg or f < 0, pos or f > 0, home

    # ------------------------------------------------------------------ CAN side (served drive)
    def attach_slave(self, slave: Any) -> None:
        """Serve the frame-level effects on ``slave``'s frames: lost RPDOs, lost master heartbeat, bus-off
        (nothing in or out)."""
        receive, send = slave.receive, slave.send

        def filtered_receive(msg: Any) -> None:
            if self._bus_off:
                return
            cob = msg.arbitration_id
            if self._drop_rpdo and cob in slave.pdo.rpdo_by_cob:
                return
            if self._drop_heartbeat and cob in slave.heartbeat_consumer.monitors:
                return
            receive(msg)

        def filtered_send(cob_id: int, data: bytes | bytearray) -> None:
            if self._bus_off:
                slave.counters["tx_errors"] += 1
                return
            send(cob_id, data)

        slave.receive = filtered_receive
        slave.send = filtered_send


def check_channel_value(index: int, value: int) -> None:
    """The register-style channel's value checks (CANopen 0x5FF0..0x5FF3, the same values on Modbus
    40600..): kind numbers to inject / clear (0 / 0xFF clear all), duty [per mille], period [ms]. Raises
    :class:`InjectionRefused` (0x06090030) naming what was expected."""
    if index == OBJ_INJECT and value not in KIND_NAMES:
        raise InjectionRefused(ABORT_VALUE_INVALID, f"unknown fault kind number {value} (1..{len(KINDS)})")
    if index == OBJ_CLEAR and value not in KIND_NAMES and value not in (0, 0xFF):
        raise InjectionRefused(ABORT_VALUE_INVALID,
                               f"unknown fault kind number {value} (1..{len(KINDS)}, 0 / 255: all)")
    if index == OBJ_DUTY and not 0 <= value <= 1000:
        raise InjectionRefused(ABORT_VALUE_INVALID, f"duty is 0..1000 per mille (got {value})")
    if index == OBJ_PERIOD and not 2 <= value <= 3_600_000:
        raise InjectionRefused(ABORT_VALUE_INVALID, f"period is 2..3600000 ms (got {value})")


def channel_options(duty_permille: int, period_ms: int, magnitude: int) -> dict:
    """:meth:`FaultInjector.inject` options from the channel's integer values (duty 0 or 1000: permanent,
    magnitude 0: the kind's default)."""
    return {"duty": 1.0 if duty_permille in (0, 1000) else duty_permille / 1000.0, "period_s": period_ms / 1000.0,
            "magnitude": float(magnitude) or None}


class InjectionApp:
    """The CANopen channel: wraps the drive's CiA 402 application for the slave and serves 0x5FF0..0x5FF6.

    Writes (and writes of the drive's own injection object 0x2010) are refused with abort 0x08000022 (not in
    the present device state) unless ``allowed``; an unknown
    kind or a bad option with 0x06090030. Every other object goes to the wrapped application unchanged
    (a :class:`~virtualaxis.canopen_slave.CanopenApplication` itself)."""

    def __init__(self, app: CanopenApplication, injector: FaultInjector):
        self._app = app
        self.injector = injector
        self.setpoint_objects = app.setpoint_objects
        # the hooks without a channel object of their own are the wrapped application's (bound: RPDO hot path)
        self.begin_pdo = app.begin_pdo
        self.end_pdo = app.end_pdo
        self.on_nmt_state = app.on_nmt_state
        self.on_communication_error = app.on_communication_error
        self.on_reset = app.on_reset
        self.has_error = app.has_error

    def validate_write(self, index: int, sub: int, value: Any) -> None:
        if index == OBJ_LEGACY_INJECT and not self.injector.allowed:
            from virtualaxis.canopen_slave import SdoAbort

            raise SdoAbort(ABORT_DEVICE_STATE, "fault injection is off (serve --allow-fault-injection)")
        if index in CHANNEL_OBJECTS:
            from virtualaxis.canopen_slave import SdoAbort

            if not self.injector.allowed:
                raise SdoAbort(ABORT_DEVICE_STATE, "fault injection is off (serve --allow-fault-injection)")
            try:
                check_channel_value(index, value)
            except InjectionRefused as exc:
                raise SdoAbort(exc.code, str(exc)) from None
            return
        self._app.validate_write(index, sub, value)

    def after_write(self, index: int, sub: int, value: Any) -> None:
        if index in CHANNEL_OBJECTS:
            slave = self.injector.slave
            if index == OBJ_INJECT:
                self.injector.inject(KIND_NAMES[value], **channel_options(
                    slave.read(OBJ_DUTY, 0), slave.read(OBJ_PERIOD, 0), slave.read(OBJ_MAGNITUDE, 0)))
            elif index == OBJ_CLEAR:
                self.injector.clear(None if value in (0, 0xFF) else KIND_NAMES[value])
            self._publish()
            return
        self._app.after_write(index, sub, value)

    def before_read(self, index: int, sub: int) -> None:
        if index in CHANNEL_OBJECTS:
            self._publish()
            return
        self._app.before_read(index, sub)

    def _publish(self) -> None:
        slave = self.injector.slave
        if slave is None or (OBJ_ACTIVE, 0) not in slave.od.entries:
            return
        slave.write_entry(slave.entry(OBJ_ACTIVE, 0), self.injector.active_bits)
        slave.write_entry(slave.entry(OBJ_ALLOWED, 0), 1 if self.injector.allowed else 0)


def serve_with_injection(bus: Any, node_id: int, drive: Any, app: Any, eds_path: Any, *, allowed: bool,
                         store_path: Any = None) -> tuple[Any, FaultInjector]:
    """A CanopenSlave for ``app`` with the injection channel in front; returns (slave, injector)."""
    from virtualaxis.canopen_slave import CanopenSlave

    injector = FaultInjector(drive, allowed=allowed)
    wrapper = InjectionApp(app, injector)
    slave = CanopenSlave(bus, node_id, eds_path, app=wrapper, store_path=store_path)
    injector.slave = slave
    injector.attach_slave(slave)
    return slave, injector
