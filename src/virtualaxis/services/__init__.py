"""Plant-floor side channels of the served drives: Modbus TCP diagnostics map and MQTT telemetry.

The protocol layer knows the drive (``virtualaxis.drive.Drive`` API), never the reverse; each service runs in
its own thread / event loop so that the drive cycle never waits for a client or a broker.
"""
