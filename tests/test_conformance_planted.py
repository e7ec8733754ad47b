"""Checks against our drive with one behaviour broken (a planted defect of ``virtualaxis.conformance.mutants``,
applied in this process and undone after): the check that claims the behaviour fails and says what it saw."""

from __future__ import annotations

import canopen
import pytest

from virtualaxis.canopen_slave.slave import CanopenSlave
from virtualaxis.conformance import run_conformance
from virtualaxis.conformance.mutants import MUTANTS
from virtualaxis.drive import core
from virtualaxis.drive.core import Drive
from virtualaxis.drive.statemachine import Cia402State
from virtualaxis.testing import start_virtual_axis

pytestmark = pytest.mark.exclusive  # timing-sensitive: background jobs stopped meanwhile

SOD_ENABLE = (Cia402State.SWITCH_ON_DISABLED.value, 0xF)

#: mutant -> (the check that claims the behaviour, words its failure names, what the mutant patches)
CASES = {
    "sw_remote_cleared": ("402-SM-1", "bit 9", [(Drive, "_update_statusword")]),
    "sod_enable_operation_direct": ("402-SM-1", "switch on disabled", [(core._TRANSITIONS, SOD_ENABLE)]),
    "error_register_not_kept": ("402-FE-1", "0x1001", [(CanopenSlave, "sdo_upload")]),
    "reset_communication_keeps_pdo_parameters": ("301-NMT-3", "0x1800", [(CanopenSlave, "_power_on_values")]),
    "quick_stop_2_as_1": ("402-QS-1", "0x605A = 2", [(Drive, "_start_stop")]),
}


@pytest.mark.parametrize("mutant", list(CASES))
def test_the_check_claiming_a_behaviour_fails_a_drive_without_it(mutant):
    check_id, words, patched = CASES[mutant]
    with start_virtual_axis(transport="virtual", lockstep=True) as axis:
        net = canopen.Network()
        net.connect(**axis.bus_kwargs)
        try:
            with pytest.MonkeyPatch.context() as mp:
                for owner, name in patched:  # (restored after the defect)
                    if isinstance(owner, dict):
                        mp.setitem(owner, name, owner[name])
                    else:
                        mp.setattr(owner, name, getattr(owner, name))
                MUTANTS[mutant].apply()
                (bad,) = run_conformance(net, axis.node_id, only=check_id)
        finally:
            net.disconnect()
    assert bad.status == "fail" and words in bad.detail, (bad.status, bad.detail)
