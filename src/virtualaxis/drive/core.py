"""The CiA 402 drive around an :class:`~virtualaxis.sim.AxisSimulator`: the one drive API.

Data path of one cycle (what to read, in order):

1. RPDO -> every mapped object stored in the object table (:mod:`~virtualaxis.drive.object_table`; write
   rules :mod:`~virtualaxis.drive.commissioning`), then the reactions (:meth:`Drive.write_objects`; an SDO
   write is :meth:`Drive.write_object`): controlword -> state machine (:mod:`~virtualaxis.drive.statemachine`),
   0x6060 -> mode object;
2. :meth:`Drive.step`: cycle hooks (fault injection), then the active stop (:mod:`~virtualaxis.drive.reactions`,
   always from the actual motion) or the mode object's ``cycle`` (:mod:`~virtualaxis.drive.modes`, one module
   per mode: PP, PV, PT, HM, CSP, CSV, CST), both on the drive's
   :class:`~virtualaxis.drive.mode_context.ModeContext` -> the set-point channel with its limiters
   (:mod:`~virtualaxis.drive.setpoints`) -> plant (``AxisSimulator.advance``);
3. monitors (:mod:`~virtualaxis.drive.monitoring`: limit switches, position range, overspeed, following error,
   standstill, motor temperature, DC link; each returns its events, which the drive applies in order) and the
   mode object's target reached -> the fault manager (:mod:`~virtualaxis.drive.fault_manager`: buffer, 0x603F,
   causes, warnings, EMCY) and the state machine's fault reaction (reaction class per fault,
   :mod:`~virtualaxis.drive.faults`);
4. statusword (state bits + the mode object's bits 10/12/13) and actual values -> objects -> the CANopen
   application copies them into the OD (:mod:`~virtualaxis.drive.canopen_app`) -> TPDO.

:class:`Drive` runs the power drive state machine, the object access and the orchestration of one
position-loop cycle; the
parameters in SI units are :mod:`~virtualaxis.drive.parameters`.
Its objects (0x6xxx, 0x2xxx) live in :attr:`Drive.objects`; the CANopen application
(:mod:`virtualaxis.drive.canopen_app`) mirrors them into the slave's object dictionary, and services
(Modbus, MQTT, conformance, fault injection) use the named API: :attr:`Drive.state`,
:meth:`Drive.get_parameter` / :meth:`Drive.set_parameter`, :meth:`Drive.inject_fault` /
:meth:`Drive.clear_fault`, :attr:`Drive.faults`, :meth:`Drive.add_observer`. See docs/drive-api.md.

Thread safety: every public method takes the drive's lock; observers are called in the thread that caused
the change (normally the runtime thread) and must not block.
"""

from __future__ import annotations

import logging
import math
import struct
import threading
from collections.abc import Callable
from pathlib import Path

from virtualaxis.config import AxisConfig
from virtualaxis.drive import modes
from virtualaxis.drive import monitoring as mon
from virtualaxis.drive import reactions as rx
from virtualaxis.drive.brake import (
    OBJ_CLOSING_DELAY,
    OBJ_OPENING_DELAY,
    OBJ_OUTPUT_MASK,
    OBJ_OUTPUTS,
    SET_BRAKE,
    STO_EMCY,
    STO_INPUT_BIT,
    STO_STATUS_BIT,
    BrakeControl,
    BrakePhase,
    SafeTorqueOff,
    brake_objects,
)
from virtualaxis.drive.commissioning import (
    ABORT_DEVICE_STATE,
    ABORT_NO_OBJECT,
    ABORT_READ_ONLY,
    ABORT_VALUE_INVALID,
    ABORT_VALUE_TOO_HIGH,
    ABORT_VALUE_TOO_LOW,
    check_write_rules,
    derived_objects,
    gain_ranges,
    lead_m,
    plain_int_keys,
    power_unit_limit,
    switch_positions_m,
    value_ranges,
)
from virtualaxis.drive.fault_manager import FaultManager
from virtualaxis.drive.faults import COMMUNICATION_FAULTS, FaultRecord
from virtualaxis.drive.gain_bounds import loop_gain_bounds
from virtualaxis.drive.mode_context import ModeContext
from virtualaxis.drive.object_table import ObjectAccessError, ObjectTable
from virtualaxis.drive.objects import SPECS, clamp_to_dtype, eds_defaults, eds_limits
from virtualaxis.drive.opmodes import TORQUE_MODES, OperationMode
from virtualaxis.drive.parameters import (
    PARAMETER_INDICES,
    DriveParameters,
    current_limit,
    drive_parameters,
    loop_gains,
    named_parameter,
    parameter_scale,
)
from virtualaxis.drive.profiles import SpeedZeroDetector, WindowTimer
from virtualaxis.drive.setpoints import SetpointChannel
from virtualaxis.drive.settings import drive_settings
from virtualaxis.drive.snapshot import MODE_NAMES, PARAMETERS, DriveState
from virtualaxis.drive.statemachine import (
    STATE,
    STATE_BITS,
    TARGET_STATE,
    TRANSITION,
    Cia402State,
    Transition,
    decode,
    transition_for,
)
from virtualaxis.drive.touch_probe import LATCH_INDEX, TouchProbe
from virtualaxis.drive.units import PositionScaling
from virtualaxis.resources import project_file
from virtualaxis.sim import CONTROL_MODE, AxisSimulator
from virtualaxis.sim.simulator import end_stops

S = STATE  # (the members as plain attributes; Cia402State is the type)
_BRAKE_IDLE = BrakePhase.IDLE
#: the SDO abort codes of the drive's write checks (:mod:`~virtualaxis.drive.commissioning`), also named here
WRITE_ABORT_CODES = (ABORT_DEVICE_STATE, ABORT_NO_OBJECT, ABORT_READ_ONLY, ABORT_VALUE_INVALID, ABORT_VALUE_TOO_HIGH,
                     ABORT_VALUE_TOO_LOW)
log = logging.getLogger("virtualaxis.drive")
DEFAULT_EDS = project_file("eds/virtualaxis.eds")

PP, PV, PT, HM, CSP, CSV, CST = (OperationMode.PP, OperationMode.PV, OperationMode.PT, OperationMode.HM,
                                 OperationMode.CSP, OperationMode.CSV, OperationMode.CST)
IP = OperationMode.IP
# objects that are two names for one value (manufacturer alias -> CiA 402 object)
ALIASES = {(0x2005, 0): (0x6065, 0), (0x2008, 0): (0x6067, 0), (0x2009, 0): (0x6068, 0)}
ALIASES_BACK = {v: k for k, v in ALIASES.items()}

#: actual-value objects written every cycle by Drive._publish_outputs, in its order (none is an alias)
_I32_MIN, _I32_MAX = -0x80000000, 0x7FFFFFFF
OUTPUT_KEYS = _OUTPUT_KEYS = ((0x6061, 0), (0x6062, 0), (0x6063, 0), (0x6064, 0), (0x606B, 0), (0x606C, 0), (0x6077, 0),
                (0x6078, 0), (0x6079, 0), (0x60F4, 0), (0x60FD, 0), (0x2020, 0), (0x2031, 0), (0x2110, 5),
                (0x6074, 0))
assert not set(_OUTPUT_KEYS) & set(ALIASES_BACK)
#: statusword base per state value: the state bits | 0x10 voltage enabled | 0x200 remote (keyed by the enum's
#: string value: hashing a str is cheaper than an Enum member, and this runs every cycle)
_STATE_SW = {state.value: bits | 0x10 | 0x200 for state, bits in STATE_BITS.items()}

#: warning EMCY of a set-point that cannot be planned (CiA 301 0x6320 parameter error; see refuse_setpoint)
SETPOINT_REFUSED_EMCY = 0x6320
#: order of the reactions to the objects of one RPDO: mode 0x6060 first, then the targets, then the controlword
#: 0x6040, then the interpolation data record 0x60C1 (judged with the frame's controlword: the record of the frame
#: that sets enable ip is the first interpolation point)
_REACTION_ORDER = {0x6060: 0, 0x6040: 2, 0x60C1: 3}
#: (state value, controlword bits 0..3) -> transition: decode + table lookup once per combination
_TRANSITIONS = {(state.value, bits): transition_for(state, decode(bits)) for state in Cia402State for bits in range(16)}


class Drive:
    """One CiA 402 servo axis. ``cycle_s`` = the position-loop cycle of the config."""

    def __init__(
        self,
        cfg: AxisConfig,
        *,
        name: str | None = None,
        eds_path: str | Path | None = DEFAULT_EDS,
        seed: int | None = None,
        initial_position_m: float = 0.0,
        discrete=None,
    ):
        self.cfg = cfg
        self.name = name or cfg.axis.name
        self.settings = drive_settings(cfg)
        #: plant positions where the negative / positive limit switch and the home switch act [m]
        self._switch_at_m = switch_positions_m(cfg, self.settings)
        self._end_stops_m = end_stops(cfg)[:2]  # plant positions of the hard end stops [m]
        self.sim = AxisSimulator(cfg, seed=seed, initial_position_m=initial_position_m, discrete=discrete)
        # compile the kernel now (a cold numba cache takes seconds), not in the first SYNC of a running bus
        AxisSimulator(cfg, seed=seed, initial_position_m=initial_position_m, discrete=self.sim.dm).advance(1)
        self.cycle_s = cfg.control.position_cycle_s
        self._lock = threading.RLock()
        has_eds = bool(eds_path) and Path(eds_path).exists()
        self._eds_defaults = eds_defaults(eds_path) if has_eds else {}
        #: value ranges of the objects (option codes, and the EDS's LowLimit / HighLimit): every write path
        #: refuses what an SDO download refuses
        self._value_ranges = value_ranges(eds_limits(eds_path) if has_eds else {})
        #: the loop gains this axis' cascade follows (speed Kp 0x2003, Kv 0x2000): larger ones are refused
        self.gain_bounds = loop_gain_bounds(cfg)
        self._range_reasons = gain_ranges(self._value_ranges, self.gain_bounds)
        #: the objects' values, aliases, changed set, shared write checks and per-cycle outputs
        self.object_table = ObjectTable(ALIASES, _OUTPUT_KEYS, self._value_ranges, self._range_reasons,
                                  plain_int_keys())
        #: set an object (and its alias) without reaction, marked changed (the table's store, bound once: the
        #: statusword and counters go through it every cycle)
        self._store: Callable[[tuple[int, int], int | float], None] = self.object_table.store
        self._observers: list[Callable[[str, DriveState], None]] = []
        self.emcy_sink: Callable[[int, int, bytes], None] | None = None  # (code, register bits, data)
        self.emcy_reset_sink: Callable[[], None] | None = None
        #: (register bits): 0x1001 = the generic and class bits of the errors still active after one went
        self.error_register_sink: Callable[[int], None] | None = None
        self.counters = {
            "illegal_controlword": 0,
            "overruns": 0,
            "targets_clamped": 0,
            "faults_raised": 0,
            "cycles": 0,
            "fault_resets_refused": 0,
            "cycle_exceptions": 0,
            "setpoints_refused": 0,
        }
        self._refused_setpoint: str | None = None  # why the set-point of the write in progress was refused
        self._cycle_hooks: tuple[Callable[[Drive], None], ...] = ()  # (a new tuple on change: none built per cycle)
        self._switch_input: Callable[[bool, bool, bool], tuple[bool, bool, bool]] | None = None  # set_switch_input
        #: fault buffer, 0x603F, persistent causes, warnings and their EMCY
        self.fault_manager = FaultManager(self._store, self.counters, self._emcy, self._emcy_reset,
                                          self._error_register)
        #: the holding brake's sequence (:mod:`~virtualaxis.drive.brake`) and the safe torque off input
        self.brake = BrakeControl(self.sim.brake is not None, cfg.effects.force_offset_n != 0.0)
        self.sto = SafeTorqueOff()
        self._reset_all()

    # ================================================================================ object table
    def derived_objects(self) -> dict[tuple[int, int], int | float]:
        """Objects whose values come from the axis config (written at boot and on NMT reset node)."""
        out = derived_objects(self.cfg, self.settings, self._eds_defaults, self._switch_at_m)
        e = self.cfg.effects
        if self.sim.brake is not None:
            out.update(brake_objects(e.brake_opening_time_s, e.brake_closing_time_s))
        return out

    def _max_speed_m_s(self) -> float:
        """0x6080 max motor speed as table speed [m/s] (motor revolutions through the gear 0x6091)."""
        return float(self._obj(0x6080)) / 60.0 * self.scaling.motor_rev_travel_m

    def _inside_stroke(self, x_plant_m: float) -> float:
        """A plant position moved inside the stroke, clear of the limit switches [m]."""
        half = self.cfg.axis.stroke_m / 2 - self.settings.limit_switch_inset_m - 1e-3
        half = max(half, 0.0)
        return min(max(x_plant_m, -half), half)

    def _set_axis(self, ax) -> None:
        """The axis reading the drive, its set-point channel and its modes see from now on."""
        self._axis = self.ctx.axis = self.setpoints.axis = ax

    @property
    def actual_velocity_m_s(self) -> float:
        """The axis' actual velocity as of the last cycle [m/s] (no snapshot: cheap enough for every cycle)."""
        return self._axis.velocity_m_s

    def travel_room_m(self, direction: float) -> tuple[float, float]:
        """Room ahead of the axis in ``direction`` (its sign) [m]: (to the hardware limit switch, <= 0 once on
        or past it; to the hard end stop). A stop plans within it (:mod:`~virtualaxis.drive.reactions`)."""
        with self._lock:
            x = self._axis.position_m
            neg, pos, _ = self._switch_at_m
            lo, hi = self._end_stops_m
            if direction >= 0.0:
                return pos - x, hi - x
            return x - neg, x - lo

    def _reset_all(self) -> None:
        """Power-on state: objects to defaults (spec <- EDS <- config), state machine to SWITCH ON DISABLED."""
        with self._lock:
            values: dict[tuple[int, int], int | float] = {s.key: s.default for s in SPECS.values()}
            values.update({k: v for k, v in self._eds_defaults.items() if k in SPECS})
            values.update(self.derived_objects())
            #: the objects' values (the object table's dict: every object and alias, kept for the drive's life)
            self.objects: dict[tuple[int, int], int | float] = self.object_table.reset(values)
            self._switch_monitor = mon.LimitSwitchMonitor()  # 0x60FD bits 0/1 as last monitored
            self._range_monitor = mon.PositionRangeMonitor()
            #: demand, zero offset (the plant position that reads as 0, shifted by homing), the plant's loop and
            #: the set-point limiters
            self.setpoints = SetpointChannel(self.sim, self.cycle_s, self._switch_monitor, self._homing_owns_switches,
                                             self._params, self._store, self._target_outside)
            #: what the modes of operation and the stop ramps see of this drive
            self.ctx = ModeContext(
                objects=self.objects, setpoints=self.setpoints, cycle_s=self.cycle_s, params=self._params,
                switches=self._switches, travel_room_m=self.travel_room_m, refuse_setpoint=self.refuse_setpoint,
                accept_setpoint=self.accept_setpoint, on_homed=self._on_homed,
                stroke_m=self.cfg.axis.stroke_m, index_pulse_offset_m=self.settings.index_pulse_offset_m)
            #: touch probes 0x60B8-0x60BD, latching at the plant's inner rate (current-loop cycles)
            self.touch_probe = TouchProbe(self.sim.current_cycles_per_cycle, self.settings.index_pulse_offset_m,
                                          index_period_m=1.0)  # (the period: _configure_probe_inputs)
            self.fault_manager.reset()
            self._state = S.NOT_READY_TO_SWITCH_ON
            self._cw = 0
            self._mode = 0
            self._power = False
            self._stop: rx.StopRamp | None = None  # active stop ramp
            self.setpoints.demand_m = self.sim.state.position_m
            self.setpoints.demand_v = 0.0
            self.setpoints.last_vff = 0.0
            self._thermal = mon.MotorTemperature()
            self._vz_timer = SpeedZeroDetector()
            self._standstill = mon.StandstillMonitor()
            # the mode objects and their set-point state (0x6060 value -> mode object; see drive.modes)
            self._modes = modes.make_modes(self.cycle_s, self.setpoints.demand_m)
            self._mode_obj = self._modes[0]
            self._gen = self._modes[0].gen  # the profile generator of no mode / PP / HM
            self._hm: modes.Homing = self._modes[HM]
            self._csp: modes.CyclicPosition = self._modes[CSP]
            self.ctx.prev_position_m = self.setpoints.demand_m
            self._fe_m = 0.0
            self._index_seen_m: float | None = None
            self._update_scaling()
            self._apply_gains()
            self.sim.enable(False)
            self.setpoints.control = self.sim.mode
            self._params_dirty = True
            self.sim.set_external_force(float(self.objects[(0x2011, 0)]))
            self.setpoints.set_polarity(int(self.objects[(0x607E, 0)]))
            self.touch_probe.set_function(int(self.objects[(0x60B8, 0)]))
            self._configure_probe_inputs()
            self._set_axis(self.sim.state)
            self._refresh_params()
            self.brake.stop()
            self._update_brake_output()
            self.sto.sources.discard("terminal")  # (0x2042 is 0 again)
            if self.sto.active:
                self.fault_manager.set_warning(STO_EMCY, True, None, False)
            # transition 0 + 1 (self-test done): switch on disabled
            self._set_state(S.SWITCH_ON_DISABLED)
            self._publish_outputs()

    def power_on_reset(self) -> None:
        """NMT reset node / power-on reset: application objects back to defaults, state machine restarted,
        and the plant restored at rest where the table is, as a real axis stays where it stood (on a limit
        switch too: the master then moves it off, the drive lets it move only away); a table pressed into an
        end stop's buffer is at the buffer's surface (the buffer relaxes); a plant state that is not finite
        restarts inside the stroke. The plant time runs on."""
        with self._lock:
            x = self.sim.state.table_position_m
            if math.isfinite(x):
                lo, hi = end_stops(self.cfg)[:2]
                x = min(max(x, lo), hi)
            else:
                x = self._inside_stroke(0.0)
            self.sim.reset(x, keep_time=True)
            self._set_axis(self.sim.state)
            self._reset_all()

    @property
    def lock(self) -> threading.RLock:
        """The drive's (re-entrant) lock: while it is held no drive cycle runs and no object changes, so
        several reads give the values of one instant (a Modbus register image)."""
        return self._lock

    def read_object(self, index: int, sub: int = 0) -> int | float:
        with self._lock:
            return self.object_table.read(index, sub)

    def check_object_write(self, index: int, sub: int, value) -> None:
        """Raise :class:`ObjectAccessError` if writing ``value`` would be refused (no side effects)."""
        spec = self.object_table.check_write(index, sub, value)  # existence, access, type, value ranges
        if index == 0x60FE:
            o = self.objects
            reason = self.brake.check_output_write((index, sub), int(value), int(o[OBJ_OUTPUTS]),
                                                   int(o[OBJ_OUTPUT_MASK]), self._power)
            if reason:
                raise ObjectAccessError(ABORT_DEVICE_STATE, reason)
        if spec is not None:  # (None: an integer object without rules of its own, value in range)
            check_write_rules(spec.key, index, sub, value, self.objects, self.gain_bounds,
                              homing=self._hm.in_progress(),
                              in_operation=self._state in (S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE))

    def write_object(self, index: int, sub: int, value, *, checked: bool = False) -> None:
        """Write an object as a master would (checked, then applied with its reaction)."""
        with self._lock:
            if not checked:
                self.check_object_write(index, sub, value)
            key = self.object_table.key(index, sub)
            value = float(value) if SPECS[key].dtype == "f32" else int(value)
            self.object_table.store(key, value)
            if key[0] in PARAMETER_INDICES:
                self._params_dirty = True
            self._refused_setpoint = None
            self._react(key, value)
            if self._refused_setpoint is not None:  # stored and reacted to; the set-point it carried was not
                reason, self._refused_setpoint = self._refused_setpoint, None
                raise ObjectAccessError(ABORT_DEVICE_STATE, reason)

    def write_objects(self, items: list[tuple[int, int, int | float]], *, checked: bool = False) -> None:
        """Write several objects as ONE event (an RPDO): every value is stored first, then the reactions run
        (mode 0x6060 first, the controlword 0x6040 after the targets, the interpolation data record 0x60C1
        after the controlword), so a controlword with the new-set-point bit and the target 0x607A in one RPDO
        start the move to the NEW target, and a record 0x60C1:1 in the RPDO whose controlword sets enable ip
        (bit 4) is the first interpolation point."""
        with self._lock:
            keyed = []
            table = self.object_table
            aliases, store = table.aliases, table.store
            for index, sub, value in items:
                if not checked:
                    self.check_object_write(index, sub, value)
                key = (index, sub)
                key = aliases.get(key, key)
                value = float(value) if SPECS[key].dtype == "f32" else int(value)
                store(key, value)
                if key[0] in PARAMETER_INDICES:
                    self._params_dirty = True
                keyed.append((key, value))
            if len(keyed) > 1:
                keyed.sort(key=_reaction_rank)
            for key, value in keyed:
                self._react(key, value)
            self._refused_setpoint = None  # (an RPDO has no answer: a refused set-point sent its EMCY)

    def load_objects(self, values: dict[tuple[int, int], int | float]) -> None:
        """Take parameter values (e.g. the slave's OD after boot: EDS defaults or restored values) without
        the reactions of a master write; scaling and loop parameters are recomputed."""
        with self._lock:
            for key, value in values.items():
                spec = SPECS.get(ALIASES.get(key, key))
                if spec is None or spec.access == "ro" or key in ((0x6040, 0), (0x6060, 0)):
                    continue
                self.object_table.store(spec.key, float(value) if spec.dtype == "f32" else int(value))
            self._update_scaling()
            self._apply_gains()
            self._params_dirty = True
            self.sim.set_external_force(float(self.objects[(0x2011, 0)]))
            self.setpoints.set_polarity(int(self.objects[(0x607E, 0)]))
            self.touch_probe.set_function(int(self.objects[(0x60B8, 0)]))
            self._configure_probe_inputs()

    @property
    def outputs(self) -> tuple:
        """The actual values published by the last cycle, in the order of :data:`OUTPUT_KEYS` (0x6061 mode
        display, 0x6062 / 0x6063 / 0x6064 positions, 0x606B / 0x606C velocities, 0x6077 torque, 0x6078 current,
        0x6079 DC link, 0x60F4 following error, 0x60FD inputs, 0x2020 temperature, 0x2031 alarm, 0x2110:5
        cycles, 0x6074 torque demand). A new tuple object whenever a value changed (compare by identity to
        see whether anything did); :attr:`objects` holds the same values. These objects are not reported by
        :meth:`take_changed` after a cycle (a mirror compares this tuple instead: one comparison per value and
        cycle, no set)."""
        return self.object_table.outputs

    def changed(self) -> bool:
        """Whether an object changed since the last :meth:`take_changed` (the per-cycle actual values in
        :attr:`outputs` not counted); lock-free, for a mirror that polls often."""
        return self.object_table.changed()

    def take_changed(self) -> list[tuple[tuple[int, int], int | float]]:
        """Objects changed since the last call: ((index, sub), value), the values as of this call; the
        per-cycle actual values are in :attr:`outputs` instead (they are reported here only after a reset)."""
        if not self.object_table.changed():  # (no lock: a change being made now is taken by the next call)
            return []
        with self._lock:
            return self.object_table.take_changed()

    def store_objects(self, values: dict[tuple[int, int], int | float]) -> None:
        """Set objects without the reactions of a master write (e.g. the config-derived ones back after the
        slave's dictionary was loaded); changed ones are reported by :meth:`take_changed`."""
        with self._lock:
            self.object_table.store_all(values)

    def _obj(self, index: int, sub: int = 0):
        return self.objects[(index, sub)]

    # ================================================================================ reactions
    def _react(self, key: tuple[int, int], value) -> None:
        index = key[0]
        if index == 0x6040:
            self._on_controlword(int(value))
        elif index == 0x6060:
            self._on_mode(int(value))
        elif index == 0x607A:
            self._mode_obj.on_target_position(self.ctx, int(value) * self.setpoints.position_sign)
        elif index in (0x60FF, 0x60B1):
            self._mode_obj.on_target_velocity(self.ctx)
        elif index == 0x60C1:
            self._mode_obj.on_interpolation_data(self.ctx, int(value) * self.setpoints.position_sign)
        elif index == 0x607E:
            sign_before = self.setpoints.position_sign
            self.setpoints.set_polarity(int(value))
            if self.setpoints.position_sign != sign_before:  # the latched probe positions read as 0x6064 does
                for latch in LATCH_INDEX.values():
                    self._store((latch, 0), _i32(-int(self.objects[(latch, 0)])))
            self._publish_outputs()  # (the actual values in the new direction at once, not from the next cycle)
        elif index == 0x60B8:
            self.touch_probe.set_function(int(value))
            self._store((0x60B9, 0), self.touch_probe.status)
        elif index == 0x2014:
            self._configure_probe_inputs()
        elif index in (0x608F, 0x6091, 0x6092):
            self._update_scaling()
        elif index in (0x2000, 0x2001, 0x2002, 0x2003, 0x2004, 0x6072, 0x6073, 0x6075, 0x6076, 0x6080):
            self._apply_gains()
        elif index == 0x2010:
            if value == 0:
                self.clear_fault()
            else:
                self.inject_fault(int(value))
        elif index == 0x2011:
            self.sim.set_external_force(float(value))
        elif index == 0x60FE:
            self._update_brake_output()
        elif index == 0x2042:
            self.set_safe_torque_off("terminal", value != 0)

    def _update_scaling(self) -> None:
        o = self.objects
        self.scaling = PositionScaling(
            lead_m=lead_m(self.cfg),
            feed_units=int(o[(0x6092, 1)]),
            feed_shaft_revs=int(o[(0x6092, 2)]),
            encoder_increments=int(o[(0x608F, 1)]),
            encoder_motor_revs=int(o[(0x608F, 2)]),
            gear_motor_revs=int(o[(0x6091, 1)]),
            gear_shaft_revs=int(o[(0x6091, 2)]),
        )
        self._u = self.ctx.u = self.scaling.metres_per_unit
        self._inc_per_m = self.scaling.increments_per_metre
        self.ctx.motor_rev_travel_m = self.scaling.motor_rev_travel_m
        self._configure_probe_inputs()

    def _configure_probe_inputs(self) -> None:
        """The touch probe inputs from 0x2014 and the index pulse period (one motor revolution)."""
        o, tp = self.objects, self.touch_probe
        tp.configure_inputs((int(o[(0x2014, 1)]), int(o[(0x2014, 2)])), int(o[(0x2014, 3)]), self._u)
        tp.index_period_m = self.scaling.motor_rev_travel_m

    def _probe_cycle(self, x0_m: float, x1_m: float) -> None:
        """The touch probes over the cycle just run (feedback ``x0_m`` -> ``x1_m``, plant coordinate): latched
        positions and status into 0x60BA-0x60BD / 0x60B9 (in the master's units, polarity 0x607E)."""
        tp = self.touch_probe
        if tp.cycle(x0_m, x1_m):
            self._store((0x60B9, 0), tp.status)
        if tp.latched:
            sp = self.setpoints
            scale = sp.position_sign / self._u
            for probe, edge, x in tp.latched:
                self._store((LATCH_INDEX[(probe, edge)], 0), _i32((x - sp.zero_m) * scale))
            tp.latched.clear()

    def _apply_gains(self) -> None:
        """Loop parameters from 0x2000-0x2004 and limits 0x6072/0x6073 into the simulator."""
        self.sim.set_loop_gains(**loop_gains(self.objects, self.cfg, self._max_speed_m_s()))
        self.sim.set_loop_gains(current_limit=current_limit(self.objects, self.cfg, self.sim.torque_constant_nm_per_a,
                                                            power_unit_limit(self.cfg)))

    # ================================================================================ state machine
    def _set_state(self, new: Cia402State) -> None:
        old = self._state
        self._state = new
        self.ctx.enabled = new is S.OPERATION_ENABLED
        if new != old:
            self._update_statusword()
            self._notify("state")

    def _on_controlword(self, cw: int) -> None:
        old_cw = self._cw
        self._cw = self.ctx.cw = cw
        # fault reset: rising edge of bit 7
        if cw & 0x80 and not old_cw & 0x80:
            if self._state == S.FAULT:
                self._fault_reset()
                return
        if self._state in (S.FAULT, S.FAULT_REACTION_ACTIVE, S.NOT_READY_TO_SWITCH_ON):
            self._mode_controlword(old_cw, cw)
            return
        tr = _TRANSITIONS[(self._state._value_, cw & 0xF)]
        if tr == TRANSITION.T16 and not 5 <= int(self._obj(0x605A)) <= 8:
            tr = TRANSITION.ILLEGAL
        if tr == TRANSITION.T2 and self.sto.active:
            tr = TRANSITION.HOLD  # safe torque off: switching on inhibited
        if tr == TRANSITION.ILLEGAL:  # ignored (the state stays), counted once per new controlword value
            if cw != old_cw:
                self.counters["illegal_controlword"] += 1
                self._store((0x2110, 1), clamp_to_dtype(self.counters["illegal_controlword"], "u32"))
        elif tr not in (TRANSITION.HOLD, TRANSITION.IGNORED):
            self._do_transition(tr)
        self._mode_controlword(old_cw, cw)
        self._update_statusword()

    def _do_transition(self, tr: Transition) -> None:
        target = TARGET_STATE[tr]
        if tr in (TRANSITION.T4, TRANSITION.T3_4, TRANSITION.T16):
            self._stop = None
            self.ctx.stopping = False
            if not self._power:
                self._power_on()
            if self.brake.phase is BrakePhase.CLOSING:
                self.brake.stop()
            self._update_brake_output()
            if tr != TRANSITION.T16 and self.brake.start(BrakePhase.OPENING, int(self._obj(*OBJ_OPENING_DELAY))):
                self._set_state(S.SWITCHED_ON)  # holding, brake opening: OPERATION ENABLED after 0x2040
                return
            self._enter_mode(self._mode)
            self._set_state(target)
        elif tr in (TRANSITION.T5, TRANSITION.T8):
            option = int(self._obj(0x605C if tr == TRANSITION.T5 else 0x605B))
            if option == 1 and self._stop is not None and self._stop.then is target:
                return  # the same command again (a master's RPDO repeats it every SYNC): the ramp runs on
            if option == 1 and self.brake.phase is BrakePhase.CLOSING and self.brake.then is target:
                return  # ... or the brake is closing for it
            if option == 1 and self._power:
                self._start_stop("slow", then=target)  # state changes once stopped
            else:
                self._power_off()
                self._set_state(target)
        elif tr == TRANSITION.T11:
            option = int(self._obj(0x605A))
            kind = {
                0: "coast",
                1: "slow",
                2: "quick",
                3: "current",
                4: "current",
                5: "slow",
                6: "quick",
                7: "current",
                8: "current",
            }[option]
            self._set_state(S.QUICK_STOP_ACTIVE)
            if kind == "coast":
                self._power_off()
                self._set_state(S.SWITCH_ON_DISABLED)
            else:
                self._start_stop(kind, then=S.SWITCH_ON_DISABLED if option <= 4 else None)
        else:  # T2, T3, T6, T7, T9, T10, T12: no motion involved (T9/T12 coast)
            if tr in (TRANSITION.T9, TRANSITION.T12) or (self._power and tr in (TRANSITION.T6, TRANSITION.T10)):
                self._power_off()  # (T6 / T10 with power: while the brake opens)
            self._set_state(target)

    def _power_on(self) -> None:
        self.setpoints.demand_m = self.sim.state.position_m - self.setpoints.zero_m
        self.setpoints.demand_v = 0.0
        self.setpoints.last_vff = 0.0
        self.setpoints.set_control(CONTROL_MODE.POSITION)
        self.setpoints.send_position(self.setpoints.demand_m, 0.0, 0.0)
        self.sim.enable(True)
        self._power = self.ctx.powered = True
        self._update_brake_output()

    def _power_off(self) -> None:
        self.sim.enable(False)
        self._power = self.ctx.powered = False
        self.brake.stop()
        self._update_brake_output()  # the brake closes (it holds after its own closing time)
        self._stop = None
        self.ctx.stopping = False
        self.setpoints.demand_v = 0.0
        self._hm.run = None

    def _update_brake_output(self) -> None:
        """The brake output (:meth:`BrakeControl.released`) to the plant's brake, shown in 0x60FE:1 bit 0 (1 =
        applied) whoever drives it: a master's release that the power stage switching off ends reads 1 from
        then on, as the brake is applied."""
        o = self.objects
        outputs, mask = int(o[OBJ_OUTPUTS]), int(o[OBJ_OUTPUT_MASK])
        released = self.brake.released(self._power, outputs, mask)
        self.sim.command_brake(released)
        self._store(OBJ_OUTPUTS, (outputs & ~SET_BRAKE) | (0 if released else SET_BRAKE))

    def _brake_cycle(self) -> None:
        """A cycle of the brake opening / closing: the position held with torque; once the delay has elapsed,
        OPERATION ENABLED (opening) or the power stage off and the state the stop was for (closing)."""
        self.setpoints.set_control(CONTROL_MODE.POSITION)
        self.setpoints.position(self.setpoints.demand_m, 0.0)
        b = self.brake
        if b.phase is BrakePhase.OPENING:
            if b.tick(self.cycle_s, int(self._obj(*OBJ_OPENING_DELAY))):
                self._enter_mode(self._mode)
                self._set_state(S.OPERATION_ENABLED)
        elif b.tick(self.cycle_s, int(self._obj(*OBJ_CLOSING_DELAY))):
            then = b.then if self._state is not S.FAULT_REACTION_ACTIVE else S.FAULT
            self._power_off()
            if isinstance(then, Cia402State):
                self._set_state(then)

    def set_safe_torque_off(self, source: str, active: bool) -> None:
        """The safe torque off input from ``source`` ("terminal": 0x2042; "injected": fault injection); STO is
        active while any source demands it (see :mod:`virtualaxis.drive.brake`): torque off at once, the brake
        closed, SWITCH ON DISABLED (FAULT from a fault reaction), warning EMCY 0x5400; once it is gone the
        drive stays disabled until shutdown -> switch on -> enable operation."""
        with self._lock:
            was, now = self.sto.set(source, bool(active))
            if now and not was:
                self._stop = None
                self.ctx.stopping = False
                if self._power:
                    self._power_off()
                self.brake.stop()
                self._update_brake_output()
                if self._state is S.FAULT_REACTION_ACTIVE:
                    self._set_state(S.FAULT)
                elif self._state not in (S.FAULT, S.NOT_READY_TO_SWITCH_ON):
                    self._set_state(S.SWITCH_ON_DISABLED)
                self.set_warning(STO_EMCY, True)
            elif was and not now:
                self.set_warning(STO_EMCY, False)
            self._publish_outputs()  # (statusword bit 14 and 0x60FD bit 18 together, before the next cycle)

    def _start_stop(self, kind: str, then: Cia402State | str | None) -> None:
        """Stop FROM THE ACTUAL MOTION (see :mod:`virtualaxis.drive.reactions`); ``then``: the state once
        stopped and held (None: stay holding, e.g. quick stop 5..8; "resume": re-enter the mode)."""
        if kind == "coast":
            self._power_off()
            if isinstance(then, Cia402State):
                self._set_state(then)
            return
        self._hm.run = None  # a stop interrupts a homing run
        self._stop = rx.StopRamp.start(self.ctx, kind, then)
        self.ctx.stopping = True

    def _travel_monitors(self, ax) -> None:
        """Position range, overspeed and limit switches: each monitor returns its event, applied here."""
        pc = self._pc
        event = self._range_monitor.check((ax.position_m - self.setpoints.zero_m) * pc.inv_u)
        if event is not None:
            self._apply_monitor_event(event)
        event = mon.OverspeedMonitor.check(ax.velocity_m_s, pc.max_speed_m_s, pc.inv_u, self._power,
                                           self.fault_manager.causes.get(0x8401))
        if event is not None:
            self._apply_monitor_event(event)
        neg, pos, _ = self._switches(ax.position_m)
        warnings = self.fault_manager.warnings
        if warnings:
            for code, active in zip(mon.LIMIT_CODES, (neg, pos), strict=True):
                if not active and code in warnings:
                    self.set_warning(code, False)
        if neg or pos:
            armed = (self._power and self._state is S.OPERATION_ENABLED and self._stop is None
                     and not self._homing_owns_switches())
            event = self._switch_monitor.check(neg, pos, ax.velocity_m_s, self.setpoints.demand_v,
                                               rx.standstill_threshold_m_s(self.ctx), armed,
                                               int(self._obj(0x2013)) == 1)
            if event is not None:
                self._apply_monitor_event(event)
        else:
            self._switch_monitor.switches = 0

    def _homing_owns_switches(self) -> bool:
        """A homing run in progress searches the limit switches itself (methods 1, 2, 17, 18) and answers an
        unexpected one with a homing error (statusword bits 13/12 = 1/0) and its own braking, which the limit
        switch fault must not overtake."""
        return self._mode == HM and (self._hm.in_progress() or self._hm.stopping_after_error(self.ctx))

    def _apply_monitor_event(self, event: mon.Event) -> None:
        """A monitor's event: a fault (with its persistent cause), a cause gone, the temperature alarm changed, or
        a limit switch reached (fault, or warning + quick stop staying enabled)."""
        if isinstance(event, mon.FaultEvent):
            self._raise_fault(event.code, event.value, cause=event.cause)
        elif isinstance(event, mon.CauseCleared):
            self.fault_manager.clear_cause(event.code, event.cause)
        elif isinstance(event, mon.AlarmChanged):  # (a warning's change updates the alarm itself)
            self.fault_manager.temperature_alarm = event.number
            self.fault_manager.update_alarm()
        elif event.fault:
            self._raise_fault(event.code, event.switches)
        else:
            self.set_warning(event.code, True)
            self.setpoints.internal_limit = True
            self._start_stop("quick", then="resume")

    def _run_stop(self) -> None:
        s = self._stop
        outcome = rx.run_stop(self.ctx, s)
        if outcome is rx.StopOutcome.DONE:
            self._finish_stop(s)
        elif outcome is rx.StopOutcome.FAILED:
            self._braking_failed()

    def _braking_failed(self) -> None:
        """The axis is not at standstill within the stop's bound: fault 0x8400 (F07900), pulses off (OFF2)."""
        self._stop = None
        self.ctx.stopping = False
        v = self._axis.velocity_m_s
        self._raise_fault(0x8400, int(round(v * self._pc.inv_u)) if math.isfinite(v) else 0)
        self._power_off()
        if self._state is S.FAULT_REACTION_ACTIVE:
            self._set_state(S.FAULT)

    def _finish_stop(self, s: rx.StopRamp) -> None:
        """Stopped and held: the state change the stop was for."""
        self._stop = None
        self.ctx.stopping = False
        self._enter_mode_idle_hold()
        then = s.then
        if self._state is S.FAULT_REACTION_ACTIVE:
            then = S.FAULT
        if isinstance(then, Cia402State) and self.brake.start(BrakePhase.CLOSING, int(self._obj(*OBJ_CLOSING_DELAY)),
                                                              then):
            self._update_brake_output()  # brake closing, torque held for 0x2041, then the state change
        elif then is S.FAULT:
            self._power_off()
            self._set_state(S.FAULT)
        elif then == "resume":
            self._enter_mode(self._mode)
        elif isinstance(then, Cia402State):
            self._power_off()
            self._set_state(then)
        # None: quick stop 5..8, stay in quick stop active holding the position

    def _enter_mode_idle_hold(self) -> None:
        """The position set-point generators at rest at the demand (after a stop)."""
        p = self.setpoints.demand_m
        self._gen.profile.reset(p)
        self._gen.jerk.reset(p, 1)
        self._csp.interp.reset(p)

    # ================================================================================ faults
    def _raise_fault(
        self, code: int, value: int = 0, *, injected: bool = False, cause: str = "", emit: bool = True
    ) -> None:
        """A fault: recorded by the fault manager (buffer, 0x603F, cause, EMCY), then the state machine's reaction:
        its class (coast, quick, or 0x605E) from the actual motion."""
        info = self.fault_manager.record(code, value, self.sim.time_s, injected=injected, cause=cause, emit=emit)
        kind = rx.fault_reaction_kind(info.reaction, int(self._obj(0x605E)))
        if self._state not in (S.FAULT, S.FAULT_REACTION_ACTIVE):
            was_moving = self._power and self._state in (S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE)
            self._set_state(S.FAULT_REACTION_ACTIVE)
            if not was_moving or kind == "coast":
                self._power_off()
                self._set_state(S.FAULT)
            else:
                self._hm.run = None
                self._start_stop(kind, then=S.FAULT)
        elif self._state is S.FAULT_REACTION_ACTIVE and kind == "coast":
            # a fault that forbids braking under control (encoder, over-current) during a stop ramp: OFF2
            self._power_off()
            self._set_state(S.FAULT)
        self._notify("fault")  # after the reaction has started: the snapshot shows the fault state

    def _fault_reset(self) -> None:
        if not self.fault_manager.acknowledge():  # (refused while a cause persists)
            return
        self.ctx.fe_timer = WindowTimer()
        self.ctx.fe_exceeded = False
        self._set_state(S.SWITCH_ON_DISABLED)
        self._notify("fault_cleared")

    def inject_fault(self, code: int, value: int = 0) -> None:
        """Raise a fault with an EMCY code (HIL fault injection); its cause persists until clear_fault()."""
        with self._lock:
            if not 0 < int(code) <= 0xFFFF:
                raise ValueError(f"fault code must be 0x0001..0xFFFF (got {code})")
            self._raise_fault(int(code), value, injected=True, cause="injected")

    def clear_fault(self) -> None:
        """Remove injected causes and acknowledge (like CW bit 7): FAULT -> SWITCH ON DISABLED if no cause
        remains."""
        with self._lock:
            self.fault_manager.clear_causes("injected")
            if self._state == S.FAULT:
                self._fault_reset()

    @property
    def faults(self) -> tuple[FaultRecord, ...]:
        with self._lock:
            return tuple(self.fault_manager.records)

    def communication_error(self, kind: str, detail: int = 0) -> None:
        """Loss of control: react per 0x6007 abort connection option (0 none, 1 fault, 2 disable voltage,
        3 quick stop; CiA 402) to heartbeat / life guarding lost, RPDO timeout (0x1400+n:5), bus off, NMT
        Stopped or Reset Communication (``nmt_stopped``, ``nmt_reset_communication``) and, in the cyclic
        synchronous modes, SYNC loss (``sync_loss``: the CANopen application reports it when the drive ran
        5 communication cycles 0x1006, at least 50 ms, of its own time without SYNC; never in SYNC
        lockstep, where the plant waits for the SYNC). NMT events and SYNC loss count only while the drive
        is enabled (a master resetting communication at start-up must not fault a disabled drive)."""
        with self._lock:
            code, stack_sent_emcy = COMMUNICATION_FAULTS.get(kind, (None, True))
            if code is None:
                return
            enabled = self._power and self._state in (S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE)
            if kind.startswith("nmt_") and not enabled:
                return
            if kind == "sync_loss" and (not enabled or self._mode not in (IP, CSP, CSV, CST)):
                return
            option = int(self._obj(0x6007))
            if option == 1:
                self._raise_fault(code, detail, emit=not stack_sent_emcy)
            elif option == 2 and self._state not in (S.FAULT, S.FAULT_REACTION_ACTIVE):
                self._power_off()
                self._set_state(S.SWITCH_ON_DISABLED)
            elif option == 3 and self._state == S.OPERATION_ENABLED:
                self._do_transition(TRANSITION.T11)

    # ================================================================================ modes
    def _on_mode(self, mode: int) -> None:
        if mode == self._mode:
            return
        self._mode = mode
        self._mode_obj = self._modes.get(mode, self._modes[0])
        self._store((0x6061, 0), mode)
        if SETPOINT_REFUSED_EMCY in self.fault_manager.warnings:  # (the refused set-point was the old mode's)
            self.set_warning(SETPOINT_REFUSED_EMCY, False)
        if self._state == S.OPERATION_ENABLED and self._stop is None:
            self._enter_mode(mode)
        self._update_statusword()
        self._notify("mode")

    def _enter_mode(self, mode: int) -> None:
        """Start the active mode (``mode`` = 0x6060): the set-point state reset (the shared profile generator
        and every mode object's own state), then the mode object takes over from the actual motion
        (:meth:`virtualaxis.drive.modes.OperatingMode.enter`)."""
        ax = self._axis
        if self.setpoints.control != CONTROL_MODE.POSITION or not self._power:
            self.setpoints.demand_m = ax.position_m - self.setpoints.zero_m
        p = self.setpoints.demand_m
        self.setpoints.last_vff = 0.0
        self._gen.reset(p)
        for m in self._modes.values():  # every mode's own state at rest (PP handshake, homing run, CSP)
            m.reset(self.ctx, p)
        self.ctx.restart_target_window()
        self._mode_obj.enter(self.ctx)

    def _target_outside(self, raw_value: int) -> bool:
        """A target beyond the software limits 0x607D: counted; with 0x2012 = 1 fault 0x8612 (the target is
        refused: True), else clamped by the set-point channel (False)."""
        self.counters["targets_clamped"] += 1
        self._store((0x2110, 3), clamp_to_dtype(self.counters["targets_clamped"], "u32"))
        if int(self._obj(0x2012)) == 1:
            self._raise_fault(0x8612, raw_value)
            return True
        return False

    def _mode_controlword(self, old_cw: int, cw: int) -> None:
        """Mode-specific controlword bits 4 (new set-point / start homing), 5, 6, 8 (halt): the mode object's,
        in OPERATION ENABLED without a stop running."""
        if self._state == S.OPERATION_ENABLED and self._stop is None:
            self._mode_obj.controlword(self.ctx, old_cw, cw)

    # ================================================================================ homing
    # ================================================================================ switches
    def _switches(self, x_plant_m: float, method: int | None = None) -> tuple[bool, bool, bool]:
        """Limit switches (negative, positive) and home switch at plant position ``x_plant_m`` [m]; the home
        switch is active below its position for methods 21 / 22, above it otherwise."""
        neg_at, pos_at, h = self._switch_at_m
        home = x_plant_m <= h if method == 21 or method == 22 else x_plant_m >= h
        if self._switch_input is not None:
            return self._switch_input(x_plant_m <= neg_at, x_plant_m >= pos_at, home)
        return x_plant_m <= neg_at, x_plant_m >= pos_at, home

    def add_motor_heat(self, rise_k: float) -> None:
        """Raise the motor winding temperature by ``rise_k`` [K] (the thermal model cools it from there)."""
        with self._lock:
            self._thermal.add_heat(rise_k)

    def set_switch_input(self, fn: Callable[[bool, bool, bool], tuple[bool, bool, bool]] | None) -> None:
        """Put ``fn`` between the switch positions and the drive's inputs: it gets the (negative limit, positive
        limit, home) readings of the plant position and returns what the drive sees (fault injection forces a
        limit switch this way); ``None`` takes it away."""
        with self._lock:
            self._switch_input = fn

    # ================================================================================ cycle
    def step(self, n_cycles: int = 1) -> None:
        """Run ``n_cycles`` drive cycles (one position-loop cycle each).

        Each cycle first calls the cycle hooks (:meth:`add_cycle_hook`), then runs the drive. An exception
        in a hook or in the cycle does not escape: it is logged with its traceback (logger
        ``virtualaxis.drive``), counted (``counters["cycle_exceptions"]``, OD 0x2110:6), the power stage is
        switched off and the drive goes to FAULT with EMCY 0x6100 (internal software); the objects stay
        consistent and a fault reset clears it once the cause is gone."""
        for _ in range(n_cycles):
            with self._lock:
                try:
                    for hook in self._cycle_hooks:
                        hook(self)
                    self._cycle()
                except Exception as exc:  # noqa: BLE001 - see docstring: caught, logged, counted, faulted
                    self._cycle_failed(exc)

    def _cycle_failed(self, exc: BaseException) -> None:
        """An exception in the drive cycle: log, count, OFF2 + FAULT 0x6100 (once per fault), republish."""
        n = self.counters["cycle_exceptions"] = self.counters["cycle_exceptions"] + 1
        self._store((0x2110, 6), clamp_to_dtype(n, "u32"))
        if n <= 5 or n % 1000 == 0:
            log.error("drive %s: exception in the drive cycle (%d so far); FAULT 0x6100", self.name, n,
                      exc_info=exc)
        try:
            self._power_off()
            self._restore_plant_if_not_finite()
            self._set_axis(self.sim.state)
            if self._state is not S.FAULT or self.fault_manager.latest_code() != 0x6100:
                self._raise_fault(0x6100, n)
            self._publish_outputs()
        except Exception:  # noqa: BLE001 - the fault path itself failed: keep the statusword consistent
            log.exception("drive %s: fault handling after a cycle exception failed", self.name)
            self._state = S.FAULT
            self._store((0x6041, 0), STATE_BITS[S.FAULT] | 0x210)

    def _on_homed(self) -> None:
        """A homing run attained its home point: the actual values follow the new position reference at once
        (methods 35 / 37 are attained by the controlword that starts them, before the next cycle: a SYNC answered
        meanwhile carries the statusword that tells it and 0x6064 = 0x607C together); then the observers hear it."""
        self._publish_outputs()
        self._notify("homed")

    def _restore_plant_if_not_finite(self) -> None:
        """If the plant state holds NaN/inf (a diverged integration), put the axis at rest at the last finite
        position inside the stroke (the plant knows no fault state; it must never feed NaN upward)."""
        st = self.sim.st
        if all(math.isfinite(x) for x in st.tolist()):
            return
        x = self.ctx.prev_position_m if math.isfinite(self.ctx.prev_position_m) else 0.0
        self.sim.reset(self._inside_stroke(x), keep_time=True)

    # ================================================================================ fault injection API
    def add_cycle_hook(self, fn: Callable[[Drive], None]) -> None:
        """``fn(drive)`` at the start of every drive cycle, under the drive's lock, before the mode runs
        (fault injection, physical effects). An exception in ``fn`` is handled like any drive-cycle
        exception (FAULT 0x6100, logged)."""
        with self._lock:
            if fn not in self._cycle_hooks:
                self._cycle_hooks = (*self._cycle_hooks, fn)

    def remove_cycle_hook(self, fn: Callable[[Drive], None]) -> None:
        with self._lock:
            if fn in self._cycle_hooks:
                self._cycle_hooks = tuple(h for h in self._cycle_hooks if h != fn)

    @property
    def simulator(self) -> AxisSimulator:
        """The plant (:class:`~virtualaxis.sim.AxisSimulator`), for physical effects (external force,
        a brake, ...). Call its setters from a cycle hook or under the drive's lock."""
        return self.sim

    def raise_fault(self, code: int, value: int = 0, *, cause: str | None = None) -> None:
        """Raise a fault with EMCY ``code`` (0x0001..0xFFFF) and fault value ``value`` (r0949).

        The reaction is the fault's class in :data:`~virtualaxis.drive.faults.FAULT_TABLE`: ``coast`` (OFF2:
        encoder loss, over-current), ``quick`` (OFF3, hardware limit switch) or ``option`` (0x605E from the
        actual motion; unknown codes). With a ``cause`` name the cause persists until
        :meth:`clear_cause`: a fault reset (controlword bit 7) is refused while any cause persists."""
        with self._lock:
            if isinstance(code, bool) or not isinstance(code, int) or not 0 < code <= 0xFFFF:
                raise ValueError(f"fault code must be an integer 0x0001..0xFFFF (got {code!r})")
            self._raise_fault(code, int(value), injected=True, cause=cause or "")

    def clear_cause(self, cause: str) -> None:
        """Remove a named persistent fault cause (see :meth:`raise_fault`); the fault itself stays until a
        fault reset."""
        with self._lock:
            self.fault_manager.clear_causes(cause)

    @property
    def causes(self) -> dict[int, str]:
        """Persistent fault causes: EMCY code -> cause name."""
        with self._lock:
            return dict(self.fault_manager.causes)

    def set_warning(self, code: int, active: bool, *, alarm_number: int | None = None) -> None:
        """Set or clear a warning (CiA 402 statusword bit 7; SINAMICS alarm number in 0x2031).

        On activation an EMCY with ``code`` goes out (CiA 301 allows EMCY for warnings; the error register
        gets the code's class bits); when the last warning and no fault remain, EMCY 0x0000 (error reset).
        ``alarm_number`` defaults to the fault table's number of the code."""
        with self._lock:
            if isinstance(code, bool) or not isinstance(code, int) or not 0 < code <= 0xFFFF:
                raise ValueError(f"warning code must be an integer 0x0001..0xFFFF (got {code!r})")
            fault_active = self._state in (S.FAULT, S.FAULT_REACTION_ACTIVE)
            if self.fault_manager.set_warning(code, active, alarm_number, fault_active):
                self._update_statusword()

    @property
    def warnings(self) -> dict[int, int]:
        """Active warnings: EMCY code -> alarm number."""
        with self._lock:
            return dict(self.fault_manager.warnings)

    def _emcy(self, code: int, register_bits: int, data: bytes) -> None:
        if self.emcy_sink is not None:
            self.emcy_sink(code, register_bits, data)

    def _emcy_reset(self) -> None:
        if self.emcy_reset_sink is not None:
            self.emcy_reset_sink()

    def _error_register(self, register_bits: int) -> None:
        if self.error_register_sink is not None:
            self.error_register_sink(register_bits)

    def _cycle(self) -> None:
        dt = self.cycle_s
        if self._power:
            if self._stop is not None:
                self._run_stop()
            elif self.brake.phase is not _BRAKE_IDLE:
                self._brake_cycle()
            elif self._state == S.OPERATION_ENABLED:
                self._mode_obj.cycle(self.ctx)
            elif self._state == S.QUICK_STOP_ACTIVE:
                self.setpoints.set_control(CONTROL_MODE.POSITION)
                self.setpoints.position(self.setpoints.demand_m, 0.0)
        self.sim.advance(1)
        self.ctx.prev_position_m = self._axis.position_m
        ax = self.sim.observe()  # the same object every cycle, refreshed (see AxisSimulator.observe)
        if ax is not self._axis:
            self._set_axis(ax)
        self.counters["cycles"] += 1
        if not math.isfinite(ax.position_m + ax.velocity_m_s + ax.table_position_m + ax.current_q_a) and not (
                math.isfinite(ax.position_m) and math.isfinite(ax.velocity_m_s)
                and math.isfinite(ax.table_position_m) and math.isfinite(ax.current_q_a)):
            raise FloatingPointError(f"plant state not finite (x={ax.position_m}, v={ax.velocity_m_s})")
        if not self.touch_probe.idle:
            self._probe_cycle(self.ctx.prev_position_m, ax.position_m)
        if not self._power:
            self.setpoints.demand_m = ax.position_m - self.setpoints.zero_m
            self._gen.profile.reset(self.setpoints.demand_m)
            self._csp.interp.reset(self.setpoints.demand_m)
        if self._params_dirty:
            self._refresh_params()
        self._travel_monitors(ax)
        self._monitor(ax, dt)
        self._publish_outputs()

    def _params(self) -> DriveParameters:
        """The cached parameters, recomputed first if an object they come from was written."""
        if self._params_dirty:
            self._refresh_params()
        return self._pc

    def _refresh_params(self) -> None:
        """Monitoring parameters and limits in SI, recomputed only after an object write (not every cycle)."""
        self._pc = drive_parameters(self.objects, self._u, self._max_speed_m_s(), self.cfg, self.settings,
                                    self.cycle_s)
        self._params_dirty = False

    def _monitor(self, ax, dt: float) -> None:
        """The per-cycle monitors after the plant (:mod:`~virtualaxis.drive.monitoring`), their events applied as
        each returns them: following error and standstill (position control), target reached (the mode object's
        bit 10), speed = 0, motor temperature, DC link."""
        pc, ctx = self._pc, self.ctx
        fe_m = ax.following_error_m
        in_position_control = (
            self._power
            and self.setpoints.control == CONTROL_MODE.POSITION
            and (self._state is S.OPERATION_ENABLED or self._state is S.QUICK_STOP_ACTIVE)
        )
        if in_position_control:
            ctx.fe_exceeded, event = mon.FollowingErrorMonitor.check(fe_m, ctx.fe_timer, dt, pc)
            if event is not None:
                self._apply_monitor_event(event)
        elif ctx.fe_timer.held_s:
            ctx.fe_timer.held_s = 0.0
        event = self._standstill.check(fe_m, dt, pc,
                                       in_position_control and self.setpoints.demand_v == 0.0 and self._stop is None,
                                       self._state is S.OPERATION_ENABLED)
        if event is not None:
            self._apply_monitor_event(event)
        ctx.target_reached = self._mode_obj.target_reached(ctx, ax, dt)
        ctx.speed_zero = self._vz_timer.update(
            ax.velocity_m_s, dt, pc.velocity_threshold_m_s, pc.velocity_threshold_time_s
        )
        fm = self.fault_manager
        for event in self._thermal.check(ax.current_q_a, ax.current_d_a, dt, pc, fm.temperature_alarm,
                                         fm.causes.get(0x4310)):
            self._apply_monitor_event(event)
        for event in mon.DcLinkMonitor.check(ax.dc_link_v, pc, fm.causes):
            self._apply_monitor_event(event)

    # ================================================================================ outputs
    def _update_statusword(self) -> None:
        sw = _STATE_SW[self._state._value_]  # state bits + voltage enabled + remote
        fm = self.fault_manager
        if fm.warning or fm.alarm:
            sw |= 0x80
        ctx = self.ctx
        if ctx.target_reached:
            sw |= 0x400
        if self.setpoints.internal_limit or (self._power and self._axis.current_limited):
            sw |= 0x800
        if self.sto.sources:
            sw |= STO_STATUS_BIT
        if self._state == S.OPERATION_ENABLED:
            mode = self._mode_obj  # bits 12 / 13 (HM: 10 too): the mode's status_mask
            sw = (sw & ~mode.status_mask) | mode.status_bits(ctx)
        elif self._state is S.QUICK_STOP_ACTIVE:
            # CiA 402 bit 10: set once the quick stop (options 5..8) has finished and the drive is halted, in
            # every mode; bit 12 only where it tells the actual motion (PV / CSV "speed = 0")
            sw = (sw & ~0x400) | (0x400 if self._stop is None else 0)
            sw |= self._mode_obj.quick_stop_bits(ctx)
        elif ((self._state is S.FAULT or self._state is S.FAULT_REACTION_ACTIVE)
              and fm.latest_code() == 0x8611):
            sw |= 0x2000  # following error (bit 13) from the timeout 0x6066 on: through the fault reaction, in FAULT
        self._store((0x6041, 0), sw)

    def _torque_actual_nm(self, ax) -> float:
        """Torque actual value [N m] as a drive computes it: from the measured dq currents (k_t i_q plus the
        reluctance torque 1.5 p (L_d - L_q) i_d i_q; cogging is not in the currents), shown within the torque
        limit 0x6072 (the current loop overshoots its limit by a few per mille for a cycle). A force actuator
        reports its force."""
        pc = self._pc
        if not pc.pmsm:
            return ax.torque_nm
        t = pc.kt_nm_per_a * ax.current_q_a + pc.reluctance_nm_per_a2 * ax.current_d_a * ax.current_q_a
        lim = pc.max_torque_nm
        return -lim if t < -lim else lim if t > lim else t

    def _publish_outputs(self) -> None:
        """Statusword and actual values into the objects (changed ones marked for the OD mirror). Hot path:
        the output objects are no aliases, so they are compared with the last values published and only the
        changed ones stored (not via _store); the integer conversions are inlined (round, then saturate: the
        same values as :func:`_i32` / :func:`_i16`, which take over for a NaN or an infinity)."""
        ax, pc, o = self._axis, self._pc, self.objects
        self._update_statusword()
        inv_u = pc.inv_u
        sp = self.setpoints
        x = ax.position_m - sp.zero_m
        fe = ax.following_error_m if self._power and sp.control == CONTROL_MODE.POSITION else 0.0
        self._fe_m = fe
        rated_nm, rated_a = pc.rated_nm, pc.rated_a
        inv_pu = inv_u * sp.position_sign  # (polarity 0x607E: the master's direction)
        inv_vu = inv_u * sp.velocity_sign
        try:
            p_dem = round(sp.demand_m * inv_pu)
            p_inc = round(x * self._inc_per_m)
            p_act = round(x * inv_pu)
            v_dem = round(sp.demand_v * inv_vu)
            v_act = round(ax.velocity_m_s * inv_vu)
            fe_u = round(fe * inv_pu)
            torque_pm = round(self._torque_actual_nm(ax) * sp.velocity_sign / rated_nm * 1000.0) if rated_nm else 0
            current_pm = round(ax.current_q_a * sp.velocity_sign / rated_a * 1000.0) if rated_a else 0
        except (OverflowError, ValueError):  # NaN or inf (never expected: the cycle guards the plant)
            p_dem = p_inc = p_act = v_dem = v_act = fe_u = torque_pm = current_pm = None
        if p_dem is None or not (
                _I32_MIN <= p_dem <= _I32_MAX and _I32_MIN <= p_inc <= _I32_MAX and _I32_MIN <= p_act <= _I32_MAX
                and _I32_MIN <= v_dem <= _I32_MAX and _I32_MIN <= v_act <= _I32_MAX and _I32_MIN <= fe_u <= _I32_MAX
                and -0x8000 <= torque_pm <= 0x7FFF and -0x8000 <= current_pm <= 0x7FFF):
            p_dem, p_inc, p_act = _i32(sp.demand_m * inv_pu), _i32(x * self._inc_per_m), _i32(x * inv_pu)
            v_dem, v_act, fe_u = _i32(sp.demand_v * inv_vu), _i32(ax.velocity_m_s * inv_vu), _i32(fe * inv_pu)
            torque_pm = _i16(self._torque_actual_nm(ax) * sp.velocity_sign / rated_nm * 1000.0) if rated_nm else 0
            current_pm = _i16(ax.current_q_a * sp.velocity_sign / rated_a * 1000.0) if rated_a else 0
        vdc_mv = ax.dc_link_v * 1000.0
        neg, pos, home = self._switches(ax.position_m, o[(0x6098, 0)])  # (a method: fault injection wraps it)
        values = (
            self._mode, p_dem, p_inc, p_act, v_dem, v_act, torque_pm, current_pm,
            round(vdc_mv) if 0.0 <= vdc_mv <= 4294967295.0 else clamp_to_dtype(vdc_mv, "u32"),
            fe_u,
            (1 if neg else 0) | (2 if pos else 0) | (4 if home else 0) | self.touch_probe.input_bits
            | (STO_INPUT_BIT if self.sto.sources else 0),
            round(self._thermal.temperature_c * 100.0) / 100.0,  # 0.01 K steps (round(t, 2): 2x the cost)
            self.fault_manager.alarm,
            self.counters["cycles"] & 0xFFFFFFFF,
            o[(0x6074, 0)] if self._mode in TORQUE_MODES else torque_pm,  # torque demand (torque modes: theirs)
        )
        self.object_table.publish(values)

    def record_overrun(self, n: int = 1) -> None:
        """The runtime reports cycles that started late (shown in 0x2110:2 and the counters)."""
        with self._lock:
            self.counters["overruns"] += n
            self._store((0x2110, 2), clamp_to_dtype(self.counters["overruns"], "u32"))

    # ================================================================================ public API
    @property
    def cia402_state(self) -> Cia402State:
        return self._state

    @property
    def state(self) -> DriveState:
        with self._lock:
            o, _u, ax = self.objects, self._u, self._axis
            ps, vs = self.setpoints.position_sign, self.setpoints.velocity_sign  # (polarity 0x607E)
            return DriveState(
                name=self.name,
                time_s=ax.time_s,
                cycles=self.counters["cycles"],
                cia402_state=self._state.value,
                mode=self._mode,
                mode_name=MODE_NAMES.get(self._mode, str(self._mode)),
                controlword=self._cw,
                statusword=int(o[(0x6041, 0)]),
                position_demand_m=self.setpoints.demand_m * ps,
                position_actual_m=(ax.position_m - self.setpoints.zero_m) * ps,
                table_position_m=ax.table_position_m,
                velocity_demand_m_s=self.setpoints.demand_v * vs,
                velocity_actual_m_s=ax.velocity_m_s * vs,
                torque_nm=self._torque_actual_nm(ax) * vs,
                current_a=ax.current_q_a * vs,
                following_error_m=self._fe_m * ps,
                dc_link_v=ax.dc_link_v,
                motor_temperature_c=self._thermal.temperature_c,
                target_reached=bool(int(o[(0x6041, 0)]) & 0x400),
                internal_limit_active=bool(int(o[(0x6041, 0)]) & 0x800),
                warning=bool(int(o[(0x6041, 0)]) & 0x80),
                homed=self._hm.homed,
                digital_inputs=int(o[(0x60FD, 0)]),
                fault_active=self._state in (S.FAULT, S.FAULT_REACTION_ACTIVE),
                error_code=self.fault_manager.fault_code(),
                faults=tuple(self.fault_manager.records),
                alarm_number=self.fault_manager.alarm,
            )

    def parameter_names(self) -> list[str]:
        return sorted(PARAMETERS)

    def get_parameter(self, name: str) -> float:
        """A named parameter in SI units (see :data:`virtualaxis.drive.snapshot.PARAMETERS`)."""
        with self._lock:
            spec = named_parameter(name)
            return float(self.objects[(spec.index, spec.sub)]) * parameter_scale(spec, self.objects, self._u)

    def set_parameter(self, name: str, value: float) -> None:
        """Set a named parameter (SI units); refused values raise :class:`ObjectAccessError`."""
        with self._lock:
            spec = named_parameter(name)
            if name == "software_limit_reaction" and isinstance(value, str):
                value = {"clamp": 0, "fault": 1}.get(value, -1)
            raw = float(value) / parameter_scale(spec, self.objects, self._u)
            dtype = SPECS[(spec.index, spec.sub)].dtype
            if dtype != "f32":
                raw = int(round(raw))
            self.write_object(spec.index, spec.sub, raw)

    def add_observer(self, callback: Callable[[str, DriveState], None]) -> None:
        """``callback(event, state)`` on "state", "mode", "fault", "fault_cleared", "homed"."""
        with self._lock:
            self._observers.append(callback)

    def remove_observer(self, callback: Callable[[str, DriveState], None]) -> None:
        with self._lock:
            if callback in self._observers:
                self._observers.remove(callback)

    def _notify(self, event: str) -> None:
        if not self._observers:
            return
        snap = self.state
        for cb in list(self._observers):
            cb(event, snap)

    def refuse_setpoint(self, reason: str) -> None:
        """A set-point that cannot be planned (see docs/drive.md): not taken (PP: not acknowledged, the axis
        stays where its profile is), counted (``counters["setpoints_refused"]``), warning EMCY
        :data:`SETPOINT_REFUSED_EMCY` (again for every refused set-point) with statusword bit 7 until a
        set-point is accepted; a single write that carried it (SDO, Modbus, MQTT) is refused with ``reason``
        (SDO abort 0x08000022)."""
        with self._lock:
            n = self.counters["setpoints_refused"] = self.counters["setpoints_refused"] + 1
            self._refused_setpoint = reason
            if SETPOINT_REFUSED_EMCY not in self.fault_manager.warnings:
                self.set_warning(SETPOINT_REFUSED_EMCY, True)
            else:
                self.fault_manager.repeat_warning(SETPOINT_REFUSED_EMCY, struct.pack("<I", n & 0xFFFFFFFF) + b"\x00")

    def accept_setpoint(self) -> None:
        """A set-point was taken: the warning of a refused one (if any) is cleared."""
        with self._lock:
            if SETPOINT_REFUSED_EMCY in self.fault_manager.warnings:
                self.set_warning(SETPOINT_REFUSED_EMCY, False)

    def set_controlword(self, cw: int) -> None:
        self.write_object(0x6040, 0, cw)


def _reaction_rank(item: tuple[tuple[int, int], int | float]) -> int:
    return _REACTION_ORDER.get(item[0][0], 1)


def _i32(x: float) -> int:
    """``x`` rounded and saturated to INTEGER32 (NaN: 0)."""
    try:
        v = round(x)
    except (OverflowError, ValueError):  # (never expected: the cycle guards the plant; saturate, don't raise)
        return 0 if math.isnan(x) else (0x7FFFFFFF if x > 0 else -0x80000000)
    return -0x80000000 if v < -0x80000000 else 0x7FFFFFFF if v > 0x7FFFFFFF else v


def _i16(x: float) -> int:
    """``x`` rounded and saturated to INTEGER16 (NaN: 0)."""
    try:
        v = round(x)
    except (OverflowError, ValueError):
        return 0 if math.isnan(x) else (0x7FFF if x > 0 else -0x8000)
    return -0x8000 if v < -0x8000 else 0x7FFF if v > 0x7FFF else v
