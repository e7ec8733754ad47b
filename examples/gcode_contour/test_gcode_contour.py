"""A user's controller test in CI: the contour program of contour.ngc run as CSP on two virtual axes (X = node 1,
Y = node 2) in SYNC lockstep, through a real CANopen master (``virtualaxis.master.LockstepMaster``: RPDO1 =
controlword + target position, TPDO1 = statusword + actual position every SYNC), with the contour error held to a
tolerance.

    pytest examples/gcode_contour                            # passes
    GCODE_KV_X=1.0 pytest examples/gcode_contour             # X position-loop gain Kv mistuned: fails

Settings by environment: GCODE_KV_X / GCODE_KV_Y (Kv [1000/min], default: the drive's), GCODE_TOLERANCE_UM
(default 40), GCODE_TRANSPORT (virtual | udp, default virtual), GCODE_REPORT (a JSON file for the figures).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from interpolator import contour_error_mm, interpolate, parse

from virtualaxis.master import LockstepMaster

HERE = Path(__file__).resolve().parent
X, Y = 1, 2
TOLERANCE_UM = float(os.environ.get("GCODE_TOLERANCE_UM", "40"))


@pytest.mark.virtual_axis(node_id=(X, Y), lockstep=True, transport=os.environ.get("GCODE_TRANSPORT", "virtual"))
def test_contour_within_tolerance(virtual_axis):
    blocks = parse((HERE / "contour.ngc").read_text())
    path_mm = interpolate(blocks, cycle_s=0.001)
    for nid, env in ((X, "GCODE_KV_X"), (Y, "GCODE_KV_Y")):
        if os.environ.get(env):  # position-loop gain Kv [1000/min] (MD32200)
            virtual_axis.nodes[nid].sdo[0x2000].raw = float(os.environ[env])
    # CSP at 1 ms, enabled with the set-point on the actual position; one SYNC per set-point, answers awaited
    with LockstepMaster(virtual_axis.network, (X, Y), mode="csp", period_s=0.001) as master:
        origin_mm = np.array([master.position_m(X), master.position_m(Y)]) * 1e3
        trace = master.run((origin_mm + path_mm) * 1e-3)
    # trace.position_m[k]: the position at the end of the cycle that set-point k drove
    actual = trace.position_m * 1e3 - origin_mm
    err_um = contour_error_mm(path_mm, actual) * 1e3
    worst = int(np.argmax(err_um))
    report = {"cycles": len(path_mm), "max_contour_error_um": float(err_um.max()),
              "rms_contour_error_um": float(np.sqrt(np.mean(err_um**2))), "worst_at_mm": path_mm[worst].tolist(),
              "tolerance_um": TOLERANCE_UM, "kv_x": os.environ.get("GCODE_KV_X", "default"),
              "kv_y": os.environ.get("GCODE_KV_Y", "default")}
    print(json.dumps(report))
    if os.environ.get("GCODE_REPORT"):
        Path(os.environ["GCODE_REPORT"]).write_text(json.dumps(report, indent=1))
    assert err_um.max() <= TOLERANCE_UM, (
        f"contour error {err_um.max():.1f} um > {TOLERANCE_UM:g} um at X{path_mm[worst][0]:.3f} "
        f"Y{path_mm[worst][1]:.3f} (cycle {worst})")
