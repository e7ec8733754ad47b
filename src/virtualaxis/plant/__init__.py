"""Plant physics: lumped mechanics, stiffness formulas, PMSM, inverter, friction, backlash, sensors.

The plant knows nothing above it (no control, no drive, no protocol).
"""
