"""Diagnostics counters: the keys of ``CanopenSlave.counters`` and their place in OD 0x2100 / 0x2101."""

from __future__ import annotations

from virtualaxis.canopen_slave.errors import ABORT_CODES

#: (counter key, EDS ParameterName) in the order of OD 0x2100 sub-indices 1..n
COUNTERS_2100: tuple[tuple[str, str], ...] = (
    ("malformed_frames", "Malformed frames"),
    ("sdo_unknown_command", "SDO unknown command specifiers"),
    ("sdo_aborts_sent", "SDO aborts sent"),
    ("sdo_aborts_received", "SDO aborts received"),
    ("sdo_toggle_errors", "SDO toggle errors"),
    ("sdo_timeouts", "SDO timeouts"),
    ("nmt_other_node_ignored", "NMT commands for other nodes ignored"),
    ("nmt_invalid_command", "NMT invalid commands"),
    ("rpdo_length_errors", "RPDO length errors"),
    ("rpdo_timeouts", "RPDO timeouts"),
    ("rpdo_received", "RPDOs received"),
    ("tpdo_sent", "TPDOs sent"),
    ("sync_received", "SYNC received"),
    ("heartbeat_timeouts", "Heartbeat consumer timeouts"),
    ("emcy_sent", "EMCY sent"),
    ("emcy_inhibited", "EMCY delayed by inhibit time"),
    ("rx_overruns", "Receive queue overruns"),
    ("node_guard_replies", "Node guarding replies"),
    ("frames_received", "Frames received"),
    ("sdo_requests", "SDO requests"),
    ("pdo_ignored_nmt_state", "PDOs ignored (NMT state)"),
    ("sdo_ignored_stopped", "SDO requests ignored (STOPPED)"),
    ("rpdo_values_refused", "RPDO values refused"),
    ("sync_length_errors", "SYNC length errors"),
    ("internal_errors", "Internal errors"),
    ("tx_errors", "Transmit errors"),
    ("life_guarding_events", "Life guarding events"),
    ("sync_timeouts", "SYNC timeouts"),
    ("node_id_conflicts", "Frames of another node with this node-ID"),
)


def abort_key(code: int) -> str:
    """Counter key of one SDO abort code, e.g. ``sdo_abort_0x06020000``."""
    return f"sdo_abort_0x{code:08X}"


def new_counters() -> dict[str, int]:
    counters = {key: 0 for key, _name in COUNTERS_2100}
    counters.update({abort_key(code): 0 for code in ABORT_CODES})
    counters["syncs_skipped"] = 0  # SYNCs answered without their cycle (a backlog; CanopenSlave.skip_sync)
    counters["rpdos_superseded"] = 0  # their RPDOs not applied: only set-points the next SYNC replaces
    return counters
