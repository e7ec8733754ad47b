"""The drive API (state snapshot, named parameters, faults, observers) - the interface Modbus, MQTT,
conformance and fault injection use - and its agreement with what a CANopen master sees."""

from __future__ import annotations

import pytest
from test_drive_rig import rig, seed_config, seed_discrete  # noqa: F401  (fixture)

from virtualaxis.config import ConfigError
from virtualaxis.drive import Cia402State, Drive, ObjectAccessError
from virtualaxis.sim import layout as L


@pytest.fixture
def drive():
    return Drive(seed_config(), discrete=seed_discrete())


def test_power_on_state_and_snapshot(drive):
    s = drive.state
    assert s.cia402_state == "SWITCH ON DISABLED"
    assert s.statusword & 0x4F == 0x40
    assert s.mode == 0 and not s.fault_active and s.faults == ()
    assert s.dc_link_v == pytest.approx(560.0)
    d = s.as_dict()
    assert d["cia402_state"] == "SWITCH ON DISABLED" and isinstance(d["faults"], list)


def test_named_parameters_map_to_objects_with_units(drive):
    drive.set_parameter("following_error_tolerance_m", 0.0025)
    assert drive.read_object(0x6065) == 2500  # 1 position unit = 1 um
    assert drive.read_object(0x2005) == 2500  # the manufacturer alias follows
    assert drive.get_parameter("following_error_tolerance_m") == pytest.approx(0.0025)
    drive.set_parameter("kv_1000_per_min", 3.0)
    assert drive.sim.pr[L.P_KV] == pytest.approx(50.0)  # Kv 3 (1000/min) = 50 1/s in the running loop
    drive.set_parameter("current_limit_a", 25.0)
    assert drive.read_object(0x6073) == 2000  # per mille of the rated 12.5 A
    assert drive.get_parameter("current_limit_a") == pytest.approx(25.0)
    drive.set_parameter("software_limit_reaction", "fault")
    assert drive.read_object(0x2012) == 1
    assert set(drive.parameter_names()) >= {"kv_1000_per_min", "velocity_ff_factor", "speed_kp", "speed_tn_ms"}


def test_bad_parameter_values_are_refused_with_the_sdo_abort_code(drive):
    with pytest.raises(ObjectAccessError) as exc:
        drive.set_parameter("quick_stop_option", 9)
    assert exc.value.code == 0x06090031
    with pytest.raises(ObjectAccessError) as exc:
        drive.set_parameter("mode_of_operation", 5)  # mode 5 is not supported
    assert exc.value.code == 0x06090030
    with pytest.raises(ObjectAccessError) as exc:
        drive.write_object(0x6041, 0, 0)
    assert exc.value.code == 0x06010002
    with pytest.raises(KeyError, match="did you mean kv_1000_per_min"):
        drive.get_parameter("kv_1000_per_mi")


def test_observers_see_state_changes_and_faults(drive):
    events = []
    drive.add_observer(lambda event, state: events.append((event, state.cia402_state)))
    for cw in (0x06, 0x07, 0x0F):
        drive.set_controlword(cw)
    drive.inject_fault(0x3210, value=700_000)
    drive.step(3)
    assert ("state", "OPERATION ENABLED") in events
    assert ("fault", "FAULT REACTION ACTIVE") in events
    assert events[-1] == ("state", "FAULT")
    rec = drive.faults[0]
    assert (rec.emcy_code, rec.fault_number, rec.value, rec.injected) == (0x3210, 30002, 700_000, True)
    assert drive.read_object(0x2030, 1) == 30002 and drive.read_object(0x2032, 1) == 0x3210
    drive.set_controlword(0x00)
    drive.set_controlword(0x80)
    assert drive.cia402_state == Cia402State.FAULT  # the injected cause persists
    drive.clear_fault()
    assert drive.cia402_state == Cia402State.SWITCH_ON_DISABLED
    assert events[-1] == ("fault_cleared", "SWITCH ON DISABLED")
    assert drive.faults[0].acknowledged


def test_fault_buffer_keeps_the_latest_eight(drive):
    for code in (0x2310, 0x3210, 0x3220, 0x4210, 0x4310, 0x7305, 0x7320, 0x8611, 0x8612):
        drive.inject_fault(code)
    assert len(drive.faults) == 8
    assert drive.faults[0].emcy_code == 0x8612 and drive.faults[-1].emcy_code == 0x3210


def test_drive_section_of_the_config_is_validated():
    cfg = seed_config()
    bad = cfg.replace()
    bad.extra["drive"] = {"software_limit_reaction": "stop"}
    with pytest.raises(ConfigError, match="drive.software_limit_reaction"):
        Drive(bad, discrete=seed_discrete())
    bad.extra["drive"] = {"following_error_tolerance": 1.0}
    with pytest.raises(ConfigError, match="drive.following_error_tolerance: unknown key"):
        Drive(bad, discrete=seed_discrete())
    good = cfg.replace()
    good.extra["drive"] = {"following_error_tolerance_m": 0.004, "position_unit_m": 1e-7}
    d = Drive(good, discrete=seed_discrete())
    assert d.read_object(0x6092, 1) == 160_000  # 16 mm lead / 0.1 um
    assert d.read_object(0x6065) == 40_000
    assert d.get_parameter("following_error_tolerance_m") == pytest.approx(0.004)


def test_api_changes_reach_the_master_and_master_writes_reach_the_api(rig):  # noqa: F811
    """One object table: set_parameter is visible by SDO, an SDO write by get_parameter and state."""
    drive, node = rig.drive, rig.node
    drive.set_parameter("profile_velocity_m_s", 0.05)
    rig.sync(1)
    assert node.sdo[0x6081].raw == 50_000
    node.sdo[0x6065].raw = 3210
    assert drive.get_parameter("following_error_tolerance_m") == pytest.approx(0.00321)
    node.sdo[0x2000].raw = 2.5  # Kv by SDO (REAL32)
    assert drive.get_parameter("kv_1000_per_min") == pytest.approx(2.5)
    node.sdo[0x6060].raw = 8
    rig.enable()
    assert drive.state.cia402_state == "OPERATION ENABLED" and drive.state.mode == 8
    node.sdo[0x2010].raw = 0x7305  # fault injection by SDO
    rig.sync(2)
    assert drive.state.fault_active and drive.faults[0].emcy_code == 0x7305
    with pytest.raises(Exception) as exc:
        node.sdo[0x2010].raw = 0x1234  # not a known fault code
    assert getattr(exc.value, "code", None) == 0x06090030


def test_every_drive_object_is_declared_in_the_eds():
    """The slave serves the EDS: an object the drive implements but the EDS lacks would be unreachable."""
    from virtualaxis.drive.core import DEFAULT_EDS
    from virtualaxis.drive.objects import missing_from_eds

    assert missing_from_eds(DEFAULT_EDS) == []


def test_every_value_range_the_drive_enforces_is_declared_in_the_eds():
    """A bound the drive refuses beyond (option codes, a 0 that would be a search or a stop that never ends, an
    interpolation period of 0) is the EDS's LowLimit / HighLimit of the object too, so that a master or tool that
    reads the EDS knows it (e.g. 0x6099:1 / :2 and 0x60C2:1 >= 1, as 0x6083 / 0x6084)."""
    from virtualaxis.drive.commissioning import value_ranges
    from virtualaxis.drive.core import DEFAULT_EDS
    from virtualaxis.drive.objects import DTYPE_RANGES, SPECS, eds_limits

    declared = eds_limits(DEFAULT_EDS)
    undeclared = []
    for key, (low, high) in value_ranges({}).items():
        type_low, type_high = DTYPE_RANGES[SPECS[key].dtype]
        eds_low, eds_high = declared.get(key, (None, None))
        if (low > type_low and eds_low != low) or (high < type_high and eds_high != high):
            undeclared.append((f"0x{key[0]:04X}:{key[1]}", (low, high), (eds_low, eds_high)))
    assert undeclared == []
    assert declared[(0x6099, 1)][0] == declared[(0x6099, 2)][0] == declared[(0x60C2, 1)][0] == 1
