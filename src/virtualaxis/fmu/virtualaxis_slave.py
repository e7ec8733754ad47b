"""The axis as an FMI 2.0 co-simulation slave (packaged by pythonfmu; see docs/fmu.md).

This file is copied into the FMU's ``resources/`` with the axis config (``axis.toml``) and the export settings
(``fmu.json``); the FMU's binary imports it by name in the importing tool's Python, where ``virtualaxis`` must be
importable. One FMU step runs a whole number of current-loop cycles of
:class:`~virtualaxis.sim.simulator.AxisSimulator` (the compiled kernel) with the inputs held over the step; the
drive samples them at its position-loop instants.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pythonfmu
from pythonfmu.enums import Fmi2Causality, Fmi2Initial, Fmi2Status, Fmi2Variability

from virtualaxis.fmu.binary_guards import guard_wrapper_calls, hold_namespace, release_state_at_exit
from virtualaxis.fmu.settings import CONFIG_FILE, SETTINGS_FILE, STEP_TOLERANCE_CYCLES, model_identifier

# the FMU's binary releases a reference to this namespace each time it executes this script (binary_guards)
hold_namespace(globals())

#: inputs per interface: (name, unit, description); the first one is the set-point
INTERFACE_INPUTS = {
    "position": (
        ("position_setpoint_m", "m", "table position set-point (the drive's position, speed and current loops "
                                     "inside)"),
        ("velocity_feedforward_m_s", "m/s", "speed feed-forward of the position loop (table speed)"),
        ("acceleration_feedforward_m_s2", "m/s2", "acceleration feed-forward of the position loop (torque "
                                                  "feed-forward)"),
    ),
    "speed": (
        ("velocity_setpoint_m_s", "m/s", "speed set-point as table speed (the drive's speed and current loops "
                                         "inside; position loop in the importing tool)"),
    ),
    "torque": (
        ("torque_setpoint_nm", "Nm", "motor torque set-point (the drive's current loop inside; speed and "
                                      "position loops in the importing tool)"),
    ),
}
FORCE_SETPOINT = ("force_setpoint_n", "N", "actuator force set-point (the actuator's force loop inside; speed "
                                           "and position loops in the importing tool)")
EXTERNAL_FORCE = ("external_force_n", "N", "external force on the table (a load along +x)")

#: outputs from the trace row the drive samples (trace-format columns; docs of ../shared/docs/trace-format.md)
TRACE_OUTPUTS = {
    "pos_cmd": ("m", "position set-point of the sample"),
    "pos_meas": ("m", "linear scale reading (quantised, noisy, delayed as configured)"),
    "pos_fb": ("m", "position feedback the position loop uses (configured sensor, dead time, quantisation)"),
    "motor_pos": ("rad", "motor encoder reading (quantised)"),
    "vel_meas": ("m/s", "table velocity"),
    "torque_meas": ("Nm", "k_t i_q measured"),
    "current_q": ("A", "measured q current"),
    "force_drive": ("N", "actuator force"),
    "force_ext": ("N", "external force"),
    "following_error": ("m", "position set-point - position feedback"),
}

#: trace columns of the drive's position loop: outputs of the position interface only (with the speed and torque
#: interfaces the position loop is the importing tool's)
POSITION_LOOP_COLUMNS = ("pos_cmd", "following_error")


def unit_of_key(key: str) -> str:
    """The unit a config key's name carries (``lead_m`` -> ``m``; ``1`` when dimensionless)."""
    from virtualaxis.config.bounds import DIMENSIONLESS, units_for_key

    units = units_for_key(key)
    return "1" if units is DIMENSIONLESS else next(iter(units))


def config_parameters(cfg) -> list[tuple[str, str, object]]:
    """The config's numeric and boolean values as FMU parameters: (``section.key``, type, value); integers that
    do not fit an FMI Integer (32 bit) are left out."""
    import dataclasses

    out = []
    for section in ("axis", "mechanics", "backlash", "friction", "actuator", "motor", "inverter", "control",
                    "sensors", "effects", "limits", "simulation"):
        part = getattr(cfg, section)
        for f in dataclasses.fields(part):
            value = getattr(part, f.name)
            if isinstance(value, bool):
                out.append((f"{section}.{f.name}", "boolean", value))
            elif isinstance(value, int):
                if -2**31 <= value < 2**31:
                    out.append((f"{section}.{f.name}", "integer", value))
            elif isinstance(value, float) and math.isfinite(value):
                out.append((f"{section}.{f.name}", "real", value))
    return out


@guard_wrapper_calls
class VirtualAxis(pythonfmu.Fmi2Slave):
    """The configured axis (config and interface from the FMU's resources)."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        from virtualaxis.config import load_axis_config

        res = Path(self.resources or ".")
        settings = json.loads((res / SETTINGS_FILE).read_text(encoding="utf-8"))
        self.interface: str = settings["interface"]
        self.step_s: float = float(settings["step_s"])
        self.config_source: str = settings.get("config", CONFIG_FILE)
        self.base_cfg = load_axis_config(res / CONFIG_FILE)
        cfg = self.base_cfg
        self.force_actuator = cfg.actuator.kind == "force"
        self.author = "virtualaxis"
        self.modelName = model_identifier(cfg.axis.name, self.interface)
        # the binary that runs this slave frees its interpreter state twice at process exit (binary_guards)
        release_state_at_exit(res.parent / "binaries" / "linux64" / f"{self.modelName}.so")
        self.description = (f"virtualaxis axis '{cfg.axis.name}' ({self.config_source}), {self.interface} "
                            f"interface; position-loop cycle {cfg.control.position_cycle_s:g} s, current-loop cycle "
                            f"{cfg.control.current_cycle_s:g} s")
        self.default_experiment = pythonfmu.DefaultExperiment(start_time=0.0, stop_time=1.0, step_size=self.step_s)
        self.units: dict[str, str] = {}
        self.sim = None
        self.row = None  # the drive's sample at the present instant (None: to be computed)
        self.state_now = None  # the axis state at the present instant (None: to be read)
        self.t0_s = 0.0
        self.ticks = 0  # current-loop cycles run since the start
        self.within = 0  # current-loop cycles into the position-loop cycle under way (0: at its start)
        self.cycle_inputs: dict[str, float] = {}  # the inputs the drive sampled at the start of that cycle
        self.error = ""
        self.overrides: dict[str, dict] = {}
        self.values: dict[str, object] = {}
        # inputs
        inputs = INTERFACE_INPUTS[self.interface]
        if self.interface == "torque" and self.force_actuator:
            inputs = (FORCE_SETPOINT,)
        for name, unit, text in (*inputs, EXTERNAL_FORCE):
            self.values[name] = 0.0
            self._real(name, unit, text, causality=Fmi2Causality.input, variability=Fmi2Variability.continuous,
                       getter=self._value_getter(name), setter=self._input_setter(name))
        # parameters: the config's values with the units their names carry and their sources
        if self.interface != "position":
            self.values["initial_position_m"] = 0.0
            self._real("initial_position_m", "m", "table position at the start (at rest); the position "
                       "interface starts at the position set-point", causality=Fmi2Causality.parameter,
                       variability=Fmi2Variability.fixed, initial=Fmi2Initial.exact,
                       getter=self._value_getter("initial_position_m"),
                       setter=self._parameter_setter("initial_position_m"))
        for key, kind, value in config_parameters(cfg):
            self.values[key] = value
            src = cfg.sources.get(key, "unspecified")
            text = f"config {key} (source: {src})"
            common = dict(causality=Fmi2Causality.parameter, variability=Fmi2Variability.fixed,
                          initial=Fmi2Initial.exact, getter=self._value_getter(key),
                          setter=self._parameter_setter(key))
            if kind == "real":
                self._real(key, unit_of_key(key), text, **common)
            elif kind == "integer":
                self.register_variable(pythonfmu.Integer(key, description=text, **common), nested=False)
            else:
                self.register_variable(pythonfmu.Boolean(key, description=text, **common), nested=False)
        # outputs: the axis state at the communication point ...
        torque_name, torque_unit = ("actuator_force_n", "N") if self.force_actuator else ("motor_torque_nm", "Nm")
        states = (
            ("motor_angle_rad", "rad", "motor angle", "motor_angle_rad"),
            ("motor_speed_rad_s", "rad/s", "motor speed", "motor_speed_rad_s"),
            ("table_position_m", "m", "table position (true)", "table_position_m"),
            ("table_velocity_m_s", "m/s", "table velocity (true)", "velocity_m_s"),
            (torque_name, torque_unit, "actuator torque (air gap, incl. cogging) or force", "torque_nm"),
            ("current_q_a", "A", "q current (true; 0 for a force actuator)", "current_q_a"),
            ("current_d_a", "A", "d current (true)", "current_d_a"),
            ("friction_force_n", "N", "friction force", "friction_force_n"),
        )
        for name, unit, text, field in states:
            self._real(name, unit, text, causality=Fmi2Causality.output, getter=self._state_getter(field))
        # ... and the channels the drive samples at it (the trace format's columns for this kind of axis)
        from virtualaxis.sim.batch import TRACE_COLUMNS, columns_for

        for col in columns_for(cfg):
            if col in POSITION_LOOP_COLUMNS and self.interface != "position":
                continue
            unit, text = TRACE_OUTPUTS[col]
            if col == "torque_meas" and self.force_actuator:
                unit = "N"
            self._real(col, unit, f"trace column {col}: {text}", causality=Fmi2Causality.output,
                       getter=self._row_getter(TRACE_COLUMNS[col]))

    # ------------------------------------------------------------------------------------------ variables
    def _real(self, name: str, unit: str, text: str, **kwargs) -> None:
        self.units[name] = unit
        self.register_variable(pythonfmu.Real(name, description=text, **kwargs), nested=False)

    def _value_getter(self, name: str):
        return lambda: self.values[name]

    def _input_setter(self, name: str):
        def setter(value):
            value = float(value)
            if not math.isfinite(value):  # refused where it is given (the axis state stays valid)
                raise ValueError(f"input {name} must be finite (got {value!r})")
            self.values[name] = value
            if self.within == 0:  # at a position-loop instant the drive samples the inputs now set
                self.row = None
        return setter

    def _parameter_setter(self, key: str):
        def setter(value):
            if self.sim is not None:
                raise RuntimeError(f"{key}: a fixed parameter; set it before initialisation ends")
            self.values[key] = value
            if key != "initial_position_m":
                section, name = key.split(".", 1)
                self.overrides.setdefault(section, {})[name] = value
        return setter

    def _state_getter(self, field: str):
        def getter():
            if self.state_now is None:
                if self.within:  # the cycle under way runs on the inputs sampled at its start
                    self._apply_inputs(self.cycle_inputs)
                self.state_now = self._simulator().state_within_cycle(self.within)
            return getattr(self.state_now, field)
        return getter

    def _row_getter(self, index: int):
        def getter():
            if self.row is None:  # (within a position-loop cycle: its sample, taken at its start)
                self._apply_inputs(self.cycle_inputs if self.within else self.values)
                self.row = self._simulator().preview()
            return float(self.row[index])
        return getter

    def to_xml(self, model_options=None):
        """The model description with each real variable's unit and the unit definitions."""
        from xml.etree.ElementTree import Element, SubElement

        root = super().to_xml(model_options or {})
        for sv in root.iter("ScalarVariable"):
            unit = self.units.get(sv.get("name"))
            real = sv.find("Real")
            if unit and real is not None:
                real.set("unit", unit)
        # outputs are calculated at initialisation: FMI 2.0 lists them as initial unknowns too
        structure = root.find("ModelStructure")
        outputs = structure.find("Outputs") if structure is not None else None
        if outputs is not None:
            initial = SubElement(structure, "InitialUnknowns")
            for unknown in outputs:
                SubElement(initial, "Unknown", {"index": unknown.get("index")})
        defs = Element("UnitDefinitions")
        for unit in sorted(set(self.units.values())):
            SubElement(defs, "Unit", {"name": unit})
        children = list(root)
        at = next(i for i, child in enumerate(children) if child.tag == "CoSimulation") + 1
        root.insert(at, defs)
        return root

    # ------------------------------------------------------------------------------------------ simulation
    def _simulator(self):
        if self.sim is None:
            from virtualaxis.sim.simulator import AxisSimulator, ControlMode

            cfg = self.base_cfg.replace(**self.overrides) if self.overrides else self.base_cfg
            if self.interface == "position":
                start = float(self.values["position_setpoint_m"])
            else:
                start = float(self.values["initial_position_m"])
            sim = AxisSimulator(cfg, initial_position_m=start)
            sim.set_mode({"position": ControlMode.POSITION, "speed": ControlMode.VELOCITY,
                          "torque": ControlMode.TORQUE}[self.interface])
            sim.enable(True)
            self.sim = sim
            self.ticks = 0
            self.within = 0
            self.row = None
            self.state_now = None
        return self.sim

    def _apply_inputs(self, v: dict) -> None:
        sim = self._simulator()
        if self.interface == "position":
            sim.set_position_setpoint(v["position_setpoint_m"], v["velocity_feedforward_m_s"],
                                      v["acceleration_feedforward_m_s2"])
        elif self.interface == "speed":
            sim.set_velocity_setpoint(v["velocity_setpoint_m_s"])
        else:
            sim.set_torque_setpoint(v["force_setpoint_n" if self.force_actuator else "torque_setpoint_nm"])
        sim.set_external_force(v["external_force_n"])

    def _fail(self, message: str) -> bool:
        self.error = message
        self.log(message, Fmi2Status.error)
        return False

    def setup_experiment(self, start_time, stop_time=None, tolerance=None):
        self.t0_s = float(start_time)

    def exit_initialization_mode(self):
        try:
            self._simulator()
        except Exception as exc:  # a parameter the config refuses: the FMU reports it and does not start
            self._fail(f"{type(exc).__name__}: {exc}")
            raise

    def do_step(self, current_time: float, step_size: float) -> bool:
        try:
            sim = self._simulator()
            hc = self.base_cfg.control.current_cycle_s
            per = sim.current_cycles_per_cycle
            k = round(step_size / hc) if math.isfinite(step_size) else 0
            if not (k >= 1 and abs(step_size / hc - k) <= STEP_TOLERANCE_CYCLES):
                return self._fail(f"communication step {step_size!r} s is not a whole number of current-loop "
                                  f"cycles ({hc:g} s, control.current_cycle_s): the kernel's unit of time")
            here = self.t0_s + self.ticks * hc
            if abs(current_time - here) > STEP_TOLERANCE_CYCLES * hc:
                return self._fail(f"doStep at t = {current_time!r} s, but the axis is at t = {here!r} s (the FMU "
                                  "steps forward only; it cannot go back or skip time)")
            left = k
            if self.within:  # finish the position-loop cycle under way (its inputs sampled at its start)
                if self.within + left < per:
                    self.within += left
                    left = 0
                else:
                    self._apply_inputs(self.cycle_inputs)
                    sim.advance(1)
                    left -= per - self.within
                    self.within = 0
            if left:  # the cycles that start in this step sample the inputs set for it
                self._apply_inputs(self.values)
                whole, self.within = divmod(left, per)
                sim.advance(whole)
                if self.within:
                    self.cycle_inputs = dict(self.values)
            self.ticks += k
            self.row = None
            self.state_now = None
            return True
        except Exception as exc:  # e.g. a non-finite input: reported to the importing tool as an error
            return self._fail(f"{type(exc).__name__}: {exc}")
