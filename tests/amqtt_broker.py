"""A pure-Python MQTT broker (amqtt, a dev dependency) for the side-channel tests on machines without mosquitto.

Run as ``python tests/amqtt_broker.py CONFIG.json``: CONFIG is amqtt's broker configuration (listeners,
plugins) as JSON. The broker runs until SIGTERM / SIGINT (clean shutdown) or SIGKILL.
"""

from __future__ import annotations

import asyncio
import json
import logging
import signal
import sys
import warnings


async def serve(config: dict) -> None:
    from amqtt.broker import Broker

    broker = Broker(config)
    await broker.start()
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    await stop.wait()
    await broker.shutdown()


def main(argv: list[str]) -> int:
    warnings.simplefilter("ignore", DeprecationWarning)
    logging.basicConfig(level=logging.ERROR, stream=sys.stderr)
    with open(argv[0], encoding="utf-8") as f:
        config = json.load(f)
    asyncio.run(serve(config))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
