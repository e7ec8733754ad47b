"""The MQTT publisher process' entry (``python -c``, started by :class:`virtualaxis.services.mqtt.MqttService`):
the JSON topics' :class:`~virtualaxis.services.mqtt.Publisher` or, with ``--sparkplug``, the
:class:`~virtualaxis.services.sparkplug.SparkplugPublisher` built on it, fed from serve's shared-memory ring and
socket pair."""

from __future__ import annotations

import json
import os
import threading

from virtualaxis.services.mqtt import MqttSettings, Publisher, TelemetryRing
from virtualaxis.services.sparkplug import SparkplugPublisher


def publisher_child(msg_fd: int, ctl_fd: int, spec_json: str) -> None:
    """Entry of the publisher process (``python -c``): the two inherited socket fds (messages from serve, stop
    watch) and the spec (settings, axes, shared memory name). serve's ``stop`` message ends it cleanly (buffer
    flushed, ``offline`` sent); serve's death (EOF on the watch socket) ends it at once without a DISCONNECT,
    so that the broker publishes the last will."""
    import mmap
    from multiprocessing.connection import Connection

    spec = json.loads(spec_json)
    settings = MqttSettings(**spec["settings"])
    fd = os.open(f"/dev/shm/{spec['shm'].lstrip('/')}", os.O_RDWR)  # by path: no resource tracker (see modbus)
    try:
        mem = mmap.mmap(fd, 0)
    finally:
        os.close(fd)
    ring = TelemetryRing(memoryview(mem), len(spec["axes"]))
    if settings.sparkplug_group is not None:
        pub: Publisher = SparkplugPublisher(settings, spec["axes"], ring)
    else:
        pub = Publisher(settings, spec["axes"], ring)
    conn, ctl = Connection(msg_fd), Connection(ctl_fd)
    pub.to_serve = conn.send_bytes  # (only the event loop's thread sends: fault/set commands)

    def read_messages() -> None:
        try:
            while True:
                pub.on_message(conn.recv_bytes())
        except (EOFError, OSError):
            return

    def watch_serve() -> None:  # serve never writes here: EOF = serve closed it after our exit, or died
        try:
            ctl.recv_bytes()
        except (EOFError, OSError):
            pass
        if not pub.stopping:
            os._exit(0)  # serve died: drop the connections unannounced, the broker sends the will

    threading.Thread(target=read_messages, daemon=True).start()
    threading.Thread(target=watch_serve, daemon=True).start()
    pub.run()
    # (the memoryview is released with the process)
