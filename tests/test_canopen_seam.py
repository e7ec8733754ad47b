"""The seam between the CiA 301 stack and the CiA 402 drive.

- the slave's application is a declared :class:`CanopenApplication` (the drive's and the injection channel's
  are; one that lacks a hook is refused with a TypeError naming it, not probed for at run time);
- the stack's services are typed against narrow node protocols and import nothing of slave.py (no import loop);
- no module of the seam reads or writes another object's private members;
- the drive's object table: aliases, changed set, per-cycle outputs; fault injection forces a limit switch
  through the drive's switch input and gives it back.
"""

from __future__ import annotations

import ast
from pathlib import Path

import can
import pytest
from test_drive_rig import seed_config, seed_discrete

from virtualaxis.canopen_slave import DEFAULT_EDS_PATH, BaseApplication, CanopenApplication, CanopenSlave
from virtualaxis.drive import Drive
from virtualaxis.drive.canopen_app import Cia402Application
from virtualaxis.drive.injection import FaultInjector, InjectionApp

SRC = Path(__file__).resolve().parents[1] / "src" / "virtualaxis"
SEAM_FILES = sorted([*(SRC / "canopen_slave").glob("*.py"), *(SRC / "runtime").glob("*.py"),
                     SRC / "drive" / "canopen_app.py", SRC / "drive" / "injection.py",
                     SRC / "drive" / "object_table.py"])
SERVICES = ("sdo_server.py", "pdo.py", "sync.py", "heartbeat.py", "emcy.py", "cobid.py")


def test_the_drive_application_and_the_injection_channel_are_canopen_applications():
    drive = Drive(seed_config(), discrete=seed_discrete())
    app = Cia402Application(drive)
    wrapper = InjectionApp(app, FaultInjector(drive, allowed=True))
    assert isinstance(app, CanopenApplication) and isinstance(wrapper, CanopenApplication)
    assert wrapper.setpoint_objects == app.setpoint_objects >= {(0x607A, 0), (0x60FF, 0)}


def test_the_slave_refuses_an_application_without_every_hook():
    class Partial:  # only one hook: the slave would have to probe for the others
        def validate_write(self, index: int, sub: int, value) -> None:
            return None

    bus = can.Bus(interface="virtual", channel="seam-partial")
    try:
        with pytest.raises(TypeError, match="after_write.*begin_pdo.*setpoint_objects|setpoint_objects.*after_write"):
            CanopenSlave(bus, 5, DEFAULT_EDS_PATH, app=Partial())

        class Enough(BaseApplication):  # the hooks it does not need from the base class
            def __init__(self) -> None:
                self.writes: list[tuple[int, int, int]] = []

            def after_write(self, index: int, sub: int, value) -> None:
                self.writes.append((index, sub, value))

        app = Enough()
        slave = CanopenSlave(bus, 5, DEFAULT_EDS_PATH, app=app)
        slave.sdo_download(0x6040, 0, (6).to_bytes(2, "little"))
        assert app.writes == [(0x6040, 0, 6)]
    finally:
        bus.shutdown()


def _imports(path: Path) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
        elif isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
    return out


@pytest.mark.parametrize("name", SERVICES)
def test_a_service_of_the_slave_imports_nothing_of_the_slave(name):
    assert "virtualaxis.canopen_slave.slave" not in _imports(SRC / "canopen_slave" / name)


@pytest.mark.parametrize("path", SEAM_FILES, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_no_module_of_the_seam_touches_another_objects_private_members(path):
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")
                and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"))):
            found.append(f"line {node.lineno}: {ast.unparse(node)}")
    assert not found


def test_the_object_table_keeps_aliases_changes_and_outputs():
    drive = Drive(seed_config(), discrete=seed_discrete())
    drive.take_changed()
    assert not drive.changed()
    drive.write_object(0x2005, 0, 1234)  # following error tolerance: an alias of 0x6065
    assert drive.read_object(0x6065, 0) == drive.read_object(0x2005, 0) == 1234
    assert drive.changed()
    assert dict(drive.take_changed()) == {(0x6065, 0): 1234, (0x2005, 0): 1234}
    assert not drive.changed() and drive.take_changed() == []
    before = drive.outputs
    drive.step(1)  # the cycle counter 0x2110:5 changes: a new outputs tuple, not reported as a change
    assert drive.outputs is not before and drive.outputs[13] == drive.read_object(0x2110, 5) == 1
    assert (0x2110, 5) not in dict(drive.take_changed())
    drive.store_objects({(0x6067, 0): 77})  # no reaction, but reported
    assert dict(drive.take_changed()) == {(0x6067, 0): 77, (0x2008, 0): 77}


def test_an_injected_limit_switch_is_the_drives_switch_input_until_cleared():
    drive = Drive(seed_config(), discrete=seed_discrete())
    injector = FaultInjector(drive, allowed=True)
    drive.step(2)
    assert drive.read_object(0x60FD, 0) & 0x3 == 0
    injector.inject("limit_switch", magnitude=1.0)  # the positive one
    drive.step(2)
    assert drive.read_object(0x60FD, 0) & 0x3 == 0x2
    injector.clear("limit_switch")
    drive.step(2)
    assert drive.read_object(0x60FD, 0) & 0x3 == 0
