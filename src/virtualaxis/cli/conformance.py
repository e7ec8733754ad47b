"""``virtualaxis conformance``: CiA 301 / CiA 402 checks against any node on the bus, as a master would.

    virtualaxis conformance --can socketcan:can0 --node-id 1 --junit conformance.xml --json conformance.json
    virtualaxis conformance --can udp_multicast:239.74.163.2 --node-id 1 --only 301-SDO,limits

One line per check (id, PASS / FAIL / SKIPPED with the reason, what was sent and what came back), a summary;
exit status 1 if any check failed. See docs/conformance.md for the check list.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("conformance", help="CiA 301 / 402 conformance checks against a node on the bus")
    p.add_argument("--can", default="socketcan:vcan0", help="bus INTERFACE:CHANNEL (default socketcan:vcan0)")
    p.add_argument("--node-id", type=int, default=1, help="node id of the device under test (default 1)")
    p.add_argument("--eds", default=None, help="the node's EDS (default: eds/virtualaxis.eds)")
    p.add_argument("--only", default=None, metavar="IDS",
                   help="comma-separated check ids, id prefixes or families (e.g. 301-SDO,limits)")
    p.add_argument("--units-per-mm", type=float, default=1000.0,
                   help="position units per mm of the node (default 1000: 1 unit = 1 um)")
    p.add_argument("--pacing", choices=("lockstep", "realtime"), default="lockstep",
                   help="how the node under test is paced: lockstep (it advances only on SYNC, as `virtualaxis serve "
                        "--lockstep`; timings judged in SYNC counts; default) or realtime (its own clock)")
    p.add_argument("--sdo-timeout", type=float, default=1.0, help="SDO response timeout [s] (default 1)")
    p.add_argument("--junit", default=None, help="write a JUnit XML report here")
    p.add_argument("--json", default=None, help="write a JSON report here")
    p.add_argument("--list", action="store_true", help="list the checks and exit")
    p.add_argument("--force", action="store_true", help="overwrite existing --junit / --json files")
    p.set_defaults(func=run)


def _out_path(opt: str, value: str | None, force: bool, inputs: list) -> Path | None:
    """An output report path, checked before the bus is opened: its folder exists, and (cli.outputs) it is not a
    folder nor an input (the EDS, also through a link), the folder is writable, the file is new unless
    ``--force``."""
    if value is None:
        return None
    from virtualaxis.cli.errors import CliError
    from virtualaxis.cli.outputs import check_output_file

    parent = Path(value).parent if str(Path(value).parent) else Path(".")
    if not parent.exists():  # (a report beside the CI job's files: a missing folder is a typing mistake)
        raise CliError(f"{opt} {value}: folder {parent} does not exist")
    return check_output_file(value, force, opt, inputs=inputs)


def run(args) -> int:
    from virtualaxis.cli.errors import CliError
    from virtualaxis.conformance import runner, suite

    if args.only is not None and any(not part.strip() for part in args.only.split(",")):
        raise CliError(f"--only {args.only!r}: an empty list or item; give check ids, id prefixes or families "
                       "(e.g. 301-SDO,limits), or leave the option out for all checks")
    checks = suite.select(args.only)
    if args.list:
        for c in checks:
            pad = " " * 25
            print(f"{c.id:<14} {c.family:<9} {c.clause}\n{pad}stimulus: {c.stimulus}\n{pad}expected: {c.expected}")
        return 0
    if not checks:
        raise CliError(f"--only {args.only!r} selects no check (ids: {', '.join(c.id for c in runner.REGISTRY)})")
    if not 1 <= args.node_id <= 127:
        raise CliError(f"--node-id must be 1..127 (got {args.node_id})")
    if not 1e-6 <= args.units_per_mm <= 1e9:  # (also refuses nan and inf)
        raise CliError(f"--units-per-mm must be 1e-06 .. 1e+09 (got {args.units_per_mm})")
    if not 0.001 <= args.sdo_timeout <= 60:
        raise CliError(f"--sdo-timeout must be 0.001..60 s (got {args.sdo_timeout})")
    eds = args.eds
    if eds is not None:
        if not Path(eds).is_file():
            kind = ("file not found" if not Path(eds).exists() else "is a folder, not an EDS file"
                    if Path(eds).is_dir() else "not a regular file (a device, pipe or socket)")
            raise CliError(f"--eds {eds}: {kind}")
        from virtualaxis.canopen_slave.od import validate_eds

        validate_eds(Path(eds))
    from virtualaxis.resources import project_file

    inputs = [eds or project_file("eds/virtualaxis.eds")]
    junit = _out_path("--junit", args.junit, args.force, inputs)
    json_out = _out_path("--json", args.json, args.force, inputs)
    import logging

    from virtualaxis.master import DEFAULT_EDS, connect
    from virtualaxis.runtime import BusOpenError

    logging.getLogger("canopen").setLevel(logging.CRITICAL)  # its SDO timeouts are reported by us, once
    try:
        net = connect(args.can)
    except BusOpenError as exc:
        raise CliError(str(exc)) from None
    t0 = time.monotonic()
    try:
        ctx = runner.Context(net, args.node_id, eds or DEFAULT_EDS, sdo_timeout_s=args.sdo_timeout,
                             units_per_mm=args.units_per_mm, lockstep=args.pacing == "lockstep")
        try:
            ctx.read(0x1000)
        except Exception as exc:  # noqa: BLE001 - any failure to reach the node ends the run here
            raise CliError(f"node {args.node_id} does not answer on {args.can} (SDO read 0x1000: {exc})") from None
        problem = runner.duplicate_node_problem(ctx) or runner.pacing_problem(ctx)
        if problem:
            raise CliError(f"{problem}; no check run")
        ident = runner.identity(ctx)
        try:
            results = runner.run_checks(ctx, checks, progress=lambda r: print(runner.line(r), flush=True))
        except runner.RunStopped as exc:  # the node's SDO server is broken: an error of the run, no report
            raise CliError(f"{exc} on {args.can} ({time.monotonic() - t0:.1f} s); no report written") from None
    finally:
        net.disconnect()
    s = runner.summary(results)
    dt = time.monotonic() - t0
    retried = (f"; {s['sdo_retries']} SDO request(s) sent again after no answer in {ctx.sdo_timeout_s:g} s "
               f"({', '.join(r.id for r in results if r.sdo_retries)})" if s["sdo_retries"] else "")
    errors = f", {s['error']} run error(s) (the master or host missed a stimulus)" if s["error"] else ""
    print(f"summary: {len(results)} checks, {s['pass']} passed, {s['fail']} failed, {s['skipped']} skipped{errors} "
          f"in {dt:.1f} s (node {args.node_id} on {args.can}){retried}")
    meta = {"can": args.can, "node_id": args.node_id, "eds": eds or DEFAULT_EDS, "duration_s": round(dt, 3),
            "pacing": args.pacing, "sync_period_s": ctx.sync_period_s, "identity": ident}
    from virtualaxis.cli.outputs import atomic_path

    if junit:
        with atomic_path(junit) as tmp:  # complete or not at all
            runner.write_junit(tmp, results, properties={
                **{f"identity.{k}": v for k, v in ident.items()}, "pacing": args.pacing,
                "sync_period_s": ctx.sync_period_s, "can": args.can, "eds": eds or DEFAULT_EDS,
                "duration_s": round(dt, 3)})
    if json_out:
        with atomic_path(json_out) as tmp:
            runner.write_json(tmp, results, meta)
    sys.stdout.flush()
    return 1 if s["fail"] or s["error"] else 0
