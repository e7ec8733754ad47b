"""virtualaxis: a virtual CNC ball-screw servo axis.

Packages (arrows point one way, top to bottom):

- ``virtualaxis.cli``        command line (knows everything below)
- ``virtualaxis.diagnosis``  sim-to-real gap diagnosis (knows sim, plant, config)
- ``virtualaxis.services``   Modbus TCP / MQTT (knows drive)
- ``virtualaxis.runtime``    pacing, clocks, serving drives on a bus (knows drive)
- ``virtualaxis.canopen_slave`` CiA 301 slave stack (NMT, SDO, PDO, EMCY, heartbeat)
- ``virtualaxis.drive``      CiA 402 drive application, state/parameter/fault API (knows sim)
- ``virtualaxis.rcsa``       receptance-coupling FRF model of the screw (knows config)
- ``virtualaxis.sim``        compiled axis simulator: control cascade + plant (knows control, plant)
- ``virtualaxis.control``    digital control loops, Siemens units
- ``virtualaxis.plant``      physics: mechanics, PMSM, inverter, friction, backlash, sensors
- ``virtualaxis.config``     TOML configuration with units and sources, validated on load
"""

__version__ = "0.1.0"
