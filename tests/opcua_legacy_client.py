"""An OPC UA client that is not asyncua: python-opcua (the ``opcua`` package, a separate codebase), in a process
of its own, driven by tests/test_services_opcua.py.

    python tests/opcua_legacy_client.py URL

Browses Objects/VirtualAxis/<axis>, reads ActualValues/Position with its EngineeringUnits and EURange,
subscribes to Position and to the axis' events, prints ``subscribed``, waits for one line on stdin (the test moved
the drive meanwhile), calls Methods/InjectFault("encoder_loss"), waits for the fault event, and ends with one line
``result {json}`` holding the raw material of the test's checks.
"""

from __future__ import annotations

import json
import sys
import time

from opcua import Client, ua

NS = "urn:virtualaxis:opcua"


def main(url: str) -> dict:
    out: dict = {}
    c = Client(url, timeout=30)
    c.connect()
    try:
        idx = c.get_namespace_index(NS)
        root = c.get_objects_node().get_child(f"{idx}:VirtualAxis")
        axes = root.get_children()
        out["axes"] = [a.get_browse_name().Name for a in axes]
        axis = axes[0]
        out["tree"] = {f.get_browse_name().Name: [n.get_browse_name().Name for n in f.get_children()]
                       for f in axis.get_children() if f.get_node_class() == ua.NodeClass.Object}
        pos = axis.get_child([f"{idx}:ActualValues", f"{idx}:Position"])
        eu = pos.get_child("0:EngineeringUnits").get_value()
        rng = pos.get_child("0:EURange").get_value()
        out["position"] = {"value": pos.get_value(), "unit_id": eu.UnitId, "namespace": eu.NamespaceUri,
                           "display": eu.DisplayName.Text, "range": [rng.Low, rng.High],
                           "type_definition": pos.get_type_definition().Identifier}
        etype = c.get_node(ua.ObjectIds.BaseEventType).get_child(f"{idx}:DriveFaultEventType")

        changes: list[float] = []
        events: list[dict] = []

        class Handler:
            def datachange_notification(self, node, val, data):
                changes.append(val)

            def event_notification(self, ev):
                events.append({"kind": getattr(ev, "Kind", None), "emcy": getattr(ev, "EmcyCode", None),
                               "injected": getattr(ev, "Injected", None), "severity": ev.Severity,
                               "message": ev.Message.Text if ev.Message else None})

        sub = c.create_subscription(20, Handler())
        sub.subscribe_data_change(pos)
        sub.subscribe_events(axis, etype)
        print("subscribed", flush=True)
        sys.stdin.readline()  # the test moved the drive
        time.sleep(0.3)  # (the last samples)
        out["changes"] = list(changes)
        methods = axis.get_child(f"{idx}:Methods")
        out["inject_active"] = methods.call_method(
            f"{idx}:InjectFault", ua.Variant("encoder_loss", ua.VariantType.String),
            ua.Variant(1.0, ua.VariantType.Double), ua.Variant(1.0, ua.VariantType.Double),
            ua.Variant(0.0, ua.VariantType.Double))
        end = time.monotonic() + 10.0
        while not any(e["kind"] == "fault" for e in events) and time.monotonic() < end:
            time.sleep(0.05)
        out["events"] = list(events)
        out["fault_codes"] = axis.get_child([f"{idx}:Faults", f"{idx}:FaultCodes"]).get_value()
        sub.delete()
    finally:
        c.disconnect()
    return out


if __name__ == "__main__":
    try:
        result = main(sys.argv[1])
    except Exception as exc:  # noqa: BLE001 - reported to the test
        result = {"error": f"{type(exc).__name__}: {exc}"}
    print("result " + json.dumps(result), flush=True)
