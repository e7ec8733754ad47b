"""An OPC UA client in a process of its own (asyncua's Client), driven by tests/test_services_opcua.py.

    python tests/opcua_client.py URL SCENARIO [JSON]

Prints ``subscribed`` (scenario ``full``) when its subscriptions run, then waits for one line on stdin (the
test moved the drive meanwhile), and ends with one line ``result {json}``; every check's raw material goes into
that JSON (the test asserts on it). Scenarios:

- ``full``: browse Objects/VirtualAxis/<axis>, read units and ranges, subscribe to ActualValues/Position and to
  the axis' DriveFaultEventType events; after the go line: refused writes (status code, value after), an
  accepted one, InjectFault and the event it raises;
- ``secure``: anonymous, wrong password and right password logins against a server with --opcua-users (and with
  ``cert``/``key`` in the JSON: Basic256Sha256 SignAndEncrypt), then a write to a parameter.
"""

from __future__ import annotations

import asyncio
import json
import sys
import time

from asyncua import Client, ua

NS = "urn:virtualaxis:opcua"


async def _names(node) -> list[str]:
    return [(await c.read_browse_name()).Name for c in await node.get_children()]


async def _status_of_write(node, variant: ua.Variant) -> str:
    try:
        await node.write_value(ua.DataValue(variant))
    except ua.UaStatusCodeError as exc:
        return _code_name(exc.code)
    return "Good"


def _code_name(code: int) -> str:
    for name, value in vars(ua.StatusCodes).items():
        if value == code and not name.startswith("_"):
            return name
    return hex(code)


async def full(url: str, out: dict) -> None:
    async with Client(url, timeout=30) as c:
        idx = await c.get_namespace_index(NS)
        root = await c.nodes.objects.get_child(f"{idx}:VirtualAxis")
        axes = await root.get_children()
        out["axes"] = [(await a.read_browse_name()).Name for a in axes]
        axis = axes[0]
        tree = {}
        for folder in await axis.get_children():
            tree[(await folder.read_browse_name()).Name] = await _names(folder)
        out["tree"] = tree
        values = await axis.get_child(f"{idx}:ActualValues")
        units = {}
        for name in tree["ActualValues"]:
            var = await values.get_child(f"{idx}:{name}")
            eu = await (await var.get_child("0:EngineeringUnits")).read_value()
            rng = await (await var.get_child("0:EURange")).read_value()
            units[name] = {"unit_id": eu.UnitId, "namespace": eu.NamespaceUri, "display": eu.DisplayName.Text,
                           "range": [rng.Low, rng.High],
                           "type_definition": (await var.read_type_definition()).Identifier}
        out["units"] = units
        params = await axis.get_child(f"{idx}:Parameters")
        kv = await params.get_child(f"{idx}:kv_1000_per_min")
        kv_range = await (await kv.get_child("0:EURange")).read_value()
        out["kv_range"] = [kv_range.Low, kv_range.High]

        changes: list[tuple[float, float]] = []
        events: list[dict] = []

        class Handler:
            def datachange_notification(self, node, val, data):
                changes.append((time.monotonic(), val))

            def event_notification(self, ev):
                events.append({"kind": ev.Kind, "emcy": ev.EmcyCode, "message": ev.Message.Text,
                               "axis": ev.Axis, "injected": ev.Injected, "severity": ev.Severity,
                               "source": ev.SourceName})

        sub = await c.create_subscription(50, Handler())
        position = await values.get_child(f"{idx}:Position")
        await sub.subscribe_data_change(position)
        etype = await c.nodes.base_event_type.get_child(f"{idx}:DriveFaultEventType")
        await sub.subscribe_events(axis, etype)
        server_events = await c.create_subscription(50, Handler())  # the same events from the Server object
        await server_events.subscribe_events(c.nodes.server, etype)
        end = time.monotonic() + 10
        while not changes and time.monotonic() < end:
            await asyncio.sleep(0.05)
        print("subscribed", flush=True)
        line = await asyncio.get_running_loop().run_in_executor(None, sys.stdin.readline)
        out["master_position_m"] = float(line.split()[1])
        end = time.monotonic() + 5  # the last sample of the standstill reaches us within a publishing interval
        while time.monotonic() < end and (not changes or abs(changes[-1][1] - out["master_position_m"]) > 2e-6):
            await asyncio.sleep(0.05)
        out["changes"] = [v for _, v in changes]
        out["position_read"] = await position.read_value()

        kv_before = await kv.read_value()
        out["kv_before"] = kv_before
        last = await params.get_child(f"{idx}:LastWriteResult")
        refused = {}
        for label, node, variant in (
            ("kv_negative", kv, ua.Variant(-1.0, ua.VariantType.Double)),
            ("kv_too_high", kv, ua.Variant(1e30, ua.VariantType.Double)),
            ("kv_nan", kv, ua.Variant(float("nan"), ua.VariantType.Double)),
            ("kv_string", kv, ua.Variant("fast", ua.VariantType.String)),
            ("kv_int", kv, ua.Variant(3, ua.VariantType.Int32)),
            ("homing_method_unsupported", await params.get_child(f"{idx}:homing_method"),
             ua.Variant(99, ua.VariantType.SByte)),
            ("position", position, ua.Variant(0.1, ua.VariantType.Double)),
            ("statusword", await (await axis.get_child(f"{idx}:State")).get_child(f"{idx}:Statusword"),
             ua.Variant(0, ua.VariantType.UInt16)),
        ):
            status = await _status_of_write(node, variant)
            refused[label] = {"status": status, "after": await node.read_value(), "last": await last.read_value()}
        out["refused"] = refused
        out["kv_after_refused"] = await kv.read_value()
        out["kv_accepted"] = await _status_of_write(kv, ua.Variant(kv_before * 0.5, ua.VariantType.Double))
        out["kv_after_accepted"] = await kv.read_value()

        methods = await axis.get_child(f"{idx}:Methods")
        inject = await methods.get_child(f"{idx}:InjectFault")
        try:
            await methods.call_method(inject, ua.Variant("no_such_kind", ua.VariantType.String), 1.0, 1.0, 0.0)
            out["inject_unknown"] = "Good"
        except ua.UaStatusCodeError as exc:
            out["inject_unknown"] = _code_name(exc.code)
        try:  # an intermittent fault needs its period
            await methods.call_method(inject, ua.Variant("encoder_loss", ua.VariantType.String), 0.5, 0.0, 0.0)
            out["inject_no_period"] = "Good"
        except ua.UaStatusCodeError as exc:
            out["inject_no_period"] = _code_name(exc.code)
        # a permanent one (Duty 1) has none: PeriodS 0 is accepted
        out["inject_active"] = await methods.call_method(
            inject, ua.Variant("encoder_loss", ua.VariantType.String), 1.0, 0.0, 0.0)
        end = time.monotonic() + 10
        while sum(e["kind"] == "fault" for e in events) < 2 and time.monotonic() < end:
            await asyncio.sleep(0.05)
        out["events"] = events
        clear = await methods.get_child(f"{idx}:ClearFault")
        try:
            await methods.call_method(clear, ua.Variant(7, ua.VariantType.Int32))
            out["clear_int"] = "Good"
        except ua.UaStatusCodeError as exc:
            out["clear_int"] = _code_name(exc.code)
        out["clear_active"] = await methods.call_method(clear, ua.Variant("encoder_loss", ua.VariantType.String))
        faults = await axis.get_child(f"{idx}:Faults")
        out["fault_codes"] = await (await faults.get_child(f"{idx}:FaultCodes")).read_value()
        out["error_code"] = await (await faults.get_child(f"{idx}:ErrorCode")).read_value()


async def secure(url: str, out: dict, opts: dict) -> None:
    async def attempt(user: str | None, password: str | None) -> str:
        c = Client(url, timeout=30)
        if opts.get("cert"):
            await c.set_security_string(f"Basic256Sha256,SignAndEncrypt,{opts['client_cert']},{opts['client_key']}")
        if user is not None:
            c.set_user(user)
            c.set_password(password)
        try:
            await c.connect()
        except Exception as exc:  # noqa: BLE001 - the refusal is the result
            return f"refused: {type(exc).__name__}: {exc}"
        try:
            idx = await c.get_namespace_index(NS)
            axis = (await (await c.nodes.objects.get_child(f"{idx}:VirtualAxis")).get_children())[0]
            out["folders"] = await _names(axis)
            kv = await (await axis.get_child(f"{idx}:Parameters")).get_child(f"{idx}:kv_1000_per_min")
            before = await kv.read_value()
            out["write"] = await _status_of_write(kv, ua.Variant(before * 0.5, ua.VariantType.Double))
            out["kv_unchanged"] = (await kv.read_value()) == before
            return "connected"
        finally:
            await c.disconnect()

    out["anonymous"] = await attempt(None, None)
    out["wrong_password"] = await attempt(opts["user"], "not-" + opts["password"])
    out["right_password"] = await attempt(opts["user"], opts["password"])


def main() -> None:
    url, scenario = sys.argv[1], sys.argv[2]
    opts = json.loads(sys.argv[3]) if len(sys.argv) > 3 else {}
    out: dict = {}
    try:
        asyncio.run(full(url, out) if scenario == "full" else secure(url, out, opts))
    except Exception as exc:  # noqa: BLE001 - reported to the test with what was gathered
        out["error"] = f"{type(exc).__name__}: {exc}"
    print("result " + json.dumps(out, default=str), flush=True)


if __name__ == "__main__":
    main()
