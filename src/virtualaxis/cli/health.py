"""``virtualaxis health``: is the drive answering? For a container healthcheck or a CI wait loop.

    virtualaxis health --can udp_multicast:239.74.163.2 --node-id 1
    virtualaxis health --can socketcan:vcan0 --node-id 1 --timeout 0.5

Reads the device type 0x1000 and the statusword 0x6041 by SDO: exit 0 with one line ``ok: node N answers,
statusword 0x...., STATE`` when the node answers, exit 1 with one ``error:`` line naming the bus and node when it
does not (a live process whose drive does not answer is unhealthy), exit 2 for bad options.
"""

from __future__ import annotations

import sys

CIA402_DEVICE_TYPE = 0x0192  # low word of 0x1000 for a CiA 402 drive
STATES = ((0x4F, 0x00, "NOT READY TO SWITCH ON"), (0x4F, 0x40, "SWITCH ON DISABLED"),
          (0x6F, 0x21, "READY TO SWITCH ON"), (0x6F, 0x23, "SWITCHED ON"), (0x6F, 0x27, "OPERATION ENABLED"),
          (0x6F, 0x07, "QUICK STOP ACTIVE"), (0x4F, 0x0F, "FAULT REACTION ACTIVE"), (0x4F, 0x08, "FAULT"))


def state_name(statusword: int) -> str:
    """The CiA 402 state a statusword shows."""
    return next((name for mask, value, name in STATES if statusword & mask == value), "UNKNOWN")


def register(sub) -> None:
    p = sub.add_parser("health", help="exit 0 if the drive answers on the bus (container healthcheck)")
    p.add_argument("--can", default="socketcan:vcan0", help="bus INTERFACE:CHANNEL (default socketcan:vcan0)")
    p.add_argument("--node-id", type=int, default=1, help="node id of the drive (default 1)")
    p.add_argument("--timeout", type=float, default=1.0, help="SDO response timeout [s] (default 1)")
    p.set_defaults(func=run)


def run(args) -> int:
    import canopen

    from virtualaxis.cli.common import open_remote_node
    from virtualaxis.master import SdoTransferOverrun

    net, node = open_remote_node(args.can, args.node_id, args.timeout)
    try:
        try:
            device_type = int(node.sdo[0x1000].raw)
            statusword = int(node.sdo[0x6041].raw)
        except (canopen.SdoCommunicationError, canopen.SdoAbortedError, SdoTransferOverrun) as exc:
            print(f"error: {args.can} node {args.node_id}: the drive does not answer ({exc})", file=sys.stderr)
            return 1
    finally:
        net.disconnect()
    if device_type & 0xFFFF != CIA402_DEVICE_TYPE:
        print(f"error: {args.can} node {args.node_id}: device type 0x{device_type:08X} is not a CiA 402 drive",
              file=sys.stderr)
        return 1
    print(f"ok: node {args.node_id} answers, statusword 0x{statusword:04X}, {state_name(statusword)}")
    return 0
