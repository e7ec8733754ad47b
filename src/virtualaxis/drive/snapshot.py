"""The drive's public state snapshot and its named parameters (Siemens-style names -> OD objects)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from virtualaxis.drive.opmodes import OperationMode

MODE_NAMES = {
    OperationMode.NO_MODE: "NO MODE",
    OperationMode.PP: "PROFILED POSITION",
    OperationMode.PV: "PROFILED VELOCITY",
    OperationMode.PT: "PROFILED TORQUE",
    OperationMode.HM: "HOMING",
    OperationMode.IP: "INTERPOLATED POSITION",
    OperationMode.CSP: "CYCLIC SYNCHRONOUS POSITION",
    OperationMode.CSV: "CYCLIC SYNCHRONOUS VELOCITY",
    OperationMode.CST: "CYCLIC SYNCHRONOUS TORQUE",
}


@dataclass(frozen=True)
class DriveState:
    """A consistent snapshot of one drive, taken after a drive cycle (SI units unless named otherwise)."""

    name: str
    time_s: float  # drive (simulation) time
    cycles: int
    cia402_state: str  # e.g. "OPERATION ENABLED"
    mode: int  # 0x6061
    mode_name: str
    controlword: int  # 0x6040
    statusword: int  # 0x6041
    position_demand_m: float  # 0x6062, in the drive's (homed) coordinate
    position_actual_m: float  # 0x6064, in the drive's (homed) coordinate
    table_position_m: float  # linear-scale table position in the plant's coordinate
    velocity_demand_m_s: float
    velocity_actual_m_s: float
    torque_nm: float  # torque actual as 0x6077: from the dq currents, within 0x6072 (N for a force actuator)
    current_a: float  # q current
    following_error_m: float  # 0x60F4 (demand - actual)
    dc_link_v: float
    motor_temperature_c: float
    target_reached: bool  # statusword bit 10
    internal_limit_active: bool  # statusword bit 11
    warning: bool  # statusword bit 7
    homed: bool
    digital_inputs: int  # 0x60FD
    fault_active: bool
    error_code: int  # 0x603F in FAULT: the newest fault not yet acknowledged (0: none; a warning is not a fault)
    faults: tuple  # FaultRecord, newest first (r0945 / r0947 / r0949)
    alarm_number: int  # 0x2031 (e.g. 7910 motor temperature alarm)

    def as_dict(self) -> dict:
        d = asdict(self)
        d["faults"] = [f.as_dict() for f in self.faults]
        return d


@dataclass(frozen=True)
class ParameterSpec:
    """A named parameter: which object it is and how its SI value maps to the object's units."""

    name: str
    index: int
    sub: int
    scale: str  # "raw" | "pos" (m <-> position units, also m/s, m/s^2, m/s^3) | "torque_nm" | "current_a"
    doc: str


def _p(name: str, index: int, sub: int, scale: str, doc: str) -> ParameterSpec:
    return ParameterSpec(name, index, sub, scale, doc)


PARAMETERS: dict[str, ParameterSpec] = {
    p.name: p
    for p in (
        _p("kv_1000_per_min", 0x2000, 0, "raw", "position loop gain Kv [1000/min] (MD32200)"),
        _p("velocity_ff_factor", 0x2001, 0, "raw", "speed feed-forward weight [1] (MD32610 / p2534)"),
        _p("feedforward_mode", 0x2002, 0, "raw", "0 off, 1 speed, 2 speed + torque (MD32620)"),
        _p("speed_kp", 0x2003, 0, "raw", "speed controller P gain [N m s/rad] (p1460)"),
        _p("speed_tn_ms", 0x2004, 0, "raw", "speed controller integral time [ms] (p1462)"),
        _p("following_error_tolerance_m", 0x6065, 0, "pos", "following error window [m] (p2546)"),
        _p("following_error_time_ms", 0x6066, 0, "raw", "following error time out [ms]"),
        _p("standstill_window_m", 0x2006, 0, "pos", "standstill window [m] (p2542)"),
        _p("standstill_time_ms", 0x2007, 0, "raw", "standstill time [ms] (p2543)"),
        _p("positioning_window_m", 0x6067, 0, "pos", "position window [m] (p2544)"),
        _p("positioning_time_ms", 0x6068, 0, "raw", "position window time [ms] (p2545)"),
        _p("software_limit_min_m", 0x607D, 1, "pos", "software position limit min [m]"),
        _p("software_limit_max_m", 0x607D, 2, "pos", "software position limit max [m]"),
        _p("software_limit_reaction", 0x2012, 0, "raw", "0 clamp + bit 11, 1 fault EMCY 0x8612"),
        _p("max_profile_velocity_m_s", 0x607F, 0, "pos", "max profile velocity [m/s]"),
        _p("profile_velocity_m_s", 0x6081, 0, "pos", "PP profile velocity [m/s]"),
        _p("profile_acceleration_m_s2", 0x6083, 0, "pos", "profile acceleration [m/s^2]"),
        _p("profile_deceleration_m_s2", 0x6084, 0, "pos", "profile deceleration [m/s^2]"),
        _p("quick_stop_deceleration_m_s2", 0x6085, 0, "pos", "quick stop deceleration [m/s^2]"),
        _p("profile_jerk_m_s3", 0x60A4, 1, "pos", "profile jerk [m/s^3] (used with motion_profile_type 3)"),
        _p("motion_profile_type", 0x6086, 0, "raw", "0 trapezoid, 3 jerk limited"),
        _p("home_offset_m", 0x607C, 0, "pos", "home offset [m]"),
        _p("homing_method", 0x6098, 0, "raw", "CiA 402 homing method"),
        _p("homing_switch_speed_m_s", 0x6099, 1, "pos", "speed during search for switch [m/s]"),
        _p("homing_zero_speed_m_s", 0x6099, 2, "pos", "speed during search for zero [m/s]"),
        _p("homing_acceleration_m_s2", 0x609A, 0, "pos", "homing acceleration [m/s^2]"),
        _p("torque_limit_nm", 0x6072, 0, "torque_nm", "max torque [N m]"),
        _p("current_limit_a", 0x6073, 0, "current_a", "max current [A] (p0640)"),
        _p("quick_stop_option", 0x605A, 0, "raw", "quick stop option code 0..8"),
        _p("shutdown_option", 0x605B, 0, "raw", "shutdown option code 0..1"),
        _p("disable_operation_option", 0x605C, 0, "raw", "disable operation option code 0..1"),
        _p("halt_option", 0x605D, 0, "raw", "halt option code 1..3"),
        _p("fault_reaction_option", 0x605E, 0, "raw", "fault reaction option code 0..2"),
        _p("abort_connection_option", 0x6007, 0, "raw", "0 none, 1 fault, 2 disable voltage, 3 quick stop"),
        _p("motor_temperature_alarm_c", 0x200A, 0, "raw", "motor temperature alarm threshold [C] (p0604)"),
        _p("motor_temperature_fault_c", 0x200B, 0, "raw", "motor temperature fault threshold [C] (p0605)"),
        _p("external_force_n", 0x2011, 0, "raw", "external (cutting) force on the table [N]"),
        _p("mode_of_operation", 0x6060, 0, "raw", "0x6060 modes of operation"),
    )
}
