"""``virtualaxis fault``: inject or clear a fault on a served drive over CANopen (objects 0x5FF0..0x5FF6).

    virtualaxis fault --can udp_multicast:239.74.163.2 --node-id 1 inject encoder_loss
    virtualaxis fault --can socketcan:vcan0 --node-id 1 inject following_error --duty 0.3 --period 2
    virtualaxis fault --can socketcan:vcan0 --node-id 1 clear [KIND]
    virtualaxis fault --can socketcan:vcan0 --node-id 1 status
    virtualaxis fault --can socketcan:vcan0 --node-id 1 list

The drive must be served with ``--allow-fault-injection``; otherwise it answers abort 0x08000022, printed
as an error. See docs/fault-injection.md.
"""

from __future__ import annotations

import struct

from virtualaxis.drive.injection import (
    KIND_NAMES,
    KINDS,
    OBJ_ACTIVE,
    OBJ_ALLOWED,
    OBJ_CLEAR,
    OBJ_DUTY,
    OBJ_INJECT,
    OBJ_MAGNITUDE,
    OBJ_PERIOD,
)


def register(sub) -> None:
    p = sub.add_parser("fault", help="inject / clear a fault on a served drive (needs serve --allow-fault-injection)")
    p.add_argument("--can", default="socketcan:vcan0", help="bus INTERFACE:CHANNEL (default socketcan:vcan0)")
    p.add_argument("--node-id", type=int, default=1, help="node id of the drive (default 1)")
    p.add_argument("--timeout", type=float, default=1.0, help="SDO response timeout [s] (default 1)")
    acts = p.add_subparsers(dest="action", metavar="ACTION")
    inj = acts.add_parser("inject", help="inject a fault: " + ", ".join(KINDS))
    inj.add_argument("kind", choices=list(KINDS))
    inj.add_argument("--duty", type=float, default=1.0, help="intermittent: fraction of each period (0..1; 1 = "
                     "permanent, default)")
    inj.add_argument("--period", type=float, default=1.0, help="intermittent period [s] (default 1)")
    inj.add_argument("--magnitude", type=int, default=0, help="kind-specific: brake force [N] (following_error), "
                     "+1/-1 switch side (limit_switch), heating [K/s] (motor_overtemperature)")
    clr = acts.add_parser("clear", help="remove an injected fault (all without KIND)")
    clr.add_argument("kind", nargs="?", choices=list(KINDS))
    acts.add_parser("status", help="print the injected faults")
    acts.add_parser("list", help="the fault kinds (CAN number, EMCY) and which are injected on the node")
    p.set_defaults(func=run)


def run(args) -> int:
    import canopen

    from virtualaxis.cli.common import check_node_options, open_remote_node
    from virtualaxis.cli.errors import CliError
    from virtualaxis.master import SdoTransferOverrun

    if not args.action:
        raise CliError("fault: give an action: inject KIND, clear [KIND], status or list")
    check_node_options(args.node_id, args.timeout)
    if args.action == "inject":
        if not 0 < args.duty <= 1:
            raise CliError(f"--duty must be in (0, 1] (got {args.duty})")
        if not 0.002 <= args.period <= 3600:
            raise CliError(f"--period must be 0.002..3600 s (got {args.period})")
    net, node = open_remote_node(args.can, args.node_id, args.timeout)
    try:
        sdo = node.sdo
        try:
            if args.action == "inject":
                sdo[OBJ_DUTY].raw = round(args.duty * 1000)
                sdo[OBJ_PERIOD].raw = round(args.period * 1000)
                sdo[OBJ_MAGNITUDE].raw = args.magnitude
                sdo[OBJ_INJECT].raw = KINDS[args.kind]
                print(f"injected {args.kind} on node {args.node_id}"
                      + (f" (intermittent: duty {args.duty:g}, period {args.period:g} s)" if args.duty < 1 else ""))
            elif args.action == "clear":
                sdo[OBJ_CLEAR].raw = KINDS[args.kind] if args.kind else 0xFF
                print(f"cleared {args.kind or 'all injected faults'} on node {args.node_id}")
            bits = sdo[OBJ_ACTIVE].raw
            allowed = sdo[OBJ_ALLOWED].raw
            active = [name for n, name in KIND_NAMES.items() if bits >> (n - 1) & 1]
            if args.action == "list":
                from virtualaxis.drive.injection import EMCY_OF_KIND

                for name, number in KINDS.items():
                    emcy = "0xFF11/0xFF10" if name == "limit_switch" else f"0x{EMCY_OF_KIND[name]:04X}"
                    print(f"{number:3d}  {name:24s} EMCY {emcy:13s} {'injected' if name in active else ''}")
            print(f"node {args.node_id}: injection {'allowed' if allowed else 'refused'}; active: "
                  f"{', '.join(active) or 'none'}; 0x603F = 0x{sdo[0x603F].raw:04X}")
        except canopen.SdoAbortedError as exc:
            hint = " (serve the drive with --allow-fault-injection)" if exc.code == 0x08000022 else ""
            text = str(exc).removeprefix(f"Code 0x{exc.code:08X}").lstrip(", ")  # (canopen's text repeats the code)
            raise CliError(f"node {args.node_id} refused: SDO abort 0x{exc.code:08X}: {text}{hint}") from None
        except canopen.SdoCommunicationError as exc:
            what = "does not answer" if "No SDO response" in str(exc) else "gives no valid SDO answer"
            raise CliError(f"node {args.node_id} {what} on {args.can}: {exc}") from None
        except SdoTransferOverrun as exc:
            raise CliError(f"node {args.node_id} on {args.can}: {exc}") from None
        except (struct.error, ValueError, IndexError) as exc:  # an answer too short for the object's type
            raise CliError(f"node {args.node_id} on {args.can}: an SDO answer that does not decode as the "
                           f"object's type ({exc})") from None
    finally:
        net.disconnect()
    return 0
