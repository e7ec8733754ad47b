"""The fault manager of one drive: the fault buffer (0x2030 / 0x2032 / 0x2033, newest first, as SINAMICS
r0947 / r0945 / r0949), the error code 0x603F, the persistent fault causes (a fault reset is refused while
one holds), the warnings and alarm number (0x2031, statusword bit 7), and the EMCY messages they produce
(through the callbacks the drive gives; the CANopen stack sets the error register 0x1001 and the
pre-defined error field 0x1003 from them).

0x603F and 0x1001 follow the errors still active (CiA 301): a fault or warning that arises sets 0x603F to its
code (its EMCY sets its class bits in 0x1001); when a warning goes or a fault reset acknowledges the faults
while other errors remain, 0x603F shows the newest fault still active (not yet acknowledged), else the newest
warning still active, and 0x1001 the generic bit and the class bits of those errors only (no EMCY: 0x0000 means
that no error is left); when none is left, 0x603F = 0 and the EMCY error reset goes out.

The state machine's reaction to a fault (fault reaction active, the stop ramp, FAULT) is the drive's:
:meth:`FaultManager.record` returns the fault's table entry, whose reaction class the drive applies."""

from __future__ import annotations

import struct
from collections.abc import Callable

from virtualaxis.drive.faults import FAULT_BUFFER_LENGTH, FaultInfo, FaultRecord, fault_info
from virtualaxis.drive.objects import clamp_to_dtype

#: the alarm number of the motor-temperature warning (0x2031)
MOTOR_TEMPERATURE_ALARM = 7910


class FaultManager:
    """Fault buffer, error code, causes, warnings and EMCY of one drive.

    Given by the drive: ``store`` (an object written without reaction), ``counters`` (the drive's counters:
    ``faults_raised``, ``fault_resets_refused``), ``emcy(code, register_bits, data)``, ``emcy_reset()`` and
    ``error_register(bits)`` (0x1001 set to the generic and class bits of the application's errors still
    active, without an EMCY)."""

    def __init__(self, store: Callable[[tuple[int, int], int | float], None], counters: dict[str, int],
                 emcy: Callable[[int, int, bytes], None], emcy_reset: Callable[[], None],
                 error_register: Callable[[int], None]) -> None:
        self._store = store
        self._counters = counters
        self._emcy = emcy
        self._emcy_reset = emcy_reset
        self._error_register = error_register
        self.records: list[FaultRecord] = []  # the fault buffer, newest first
        self.causes: dict[int, str] = {}  # persistent fault causes: code -> "injected" / monitor name
        self.warnings: dict[int, int] = {}  # active warnings: EMCY code -> alarm number
        self.temperature_alarm = 0  # motor-temperature alarm number (0: none)
        self.alarm = 0  # 0x2031
        self.warning = False  # statusword bit 7

    def reset(self) -> None:
        """Power-on: no faults, causes or warnings."""
        self.records = []
        self.causes.clear()
        self.warnings.clear()
        self.temperature_alarm = 0
        self.alarm = 0
        self.warning = False

    # ------------------------------------------------------------------ faults
    def record(self, code: int, value: int, time_s: float, *, injected: bool = False, cause: str = "",
               emit: bool = True) -> FaultInfo:
        """A fault: into the buffer and 0x603F, its cause (if named) kept, its EMCY sent (``emit``); returns
        its table entry (the reaction class is the drive's to apply)."""
        info = fault_info(code)
        self.records.insert(0, FaultRecord(code, info.fault_number, int(value), info.text, time_s, injected))
        del self.records[FAULT_BUFFER_LENGTH:]
        self._counters["faults_raised"] += 1
        self._store((0x2110, 4), clamp_to_dtype(self._counters["faults_raised"], "u32"))
        self._publish_buffer()
        if cause:
            self.causes[code] = cause
        self._store((0x603F, 0), code)
        if emit:
            self._emcy(code, info.register_bits, struct.pack("<i", clamp_to_dtype(value, "i32"))[:4] + b"\x00")
        return info

    def latest_code(self) -> int | None:
        """The EMCY code of the newest fault in the buffer (None: empty)."""
        return self.records[0].emcy_code if self.records else None

    def fault_code(self) -> int:
        """The EMCY code of the newest fault not yet acknowledged (0: none), the fault a fault reset clears."""
        rec = self.records[0] if self.records else None
        return rec.emcy_code if rec is not None and not rec.acknowledged else 0

    def _publish_buffer(self) -> None:
        records = self.records
        for i in range(FAULT_BUFFER_LENGTH):
            rec = records[i] if i < len(records) else None
            self._store((0x2030, i + 1), rec.fault_number if rec else 0)
            self._store((0x2032, i + 1), rec.emcy_code if rec else 0)
            self._store((0x2033, i + 1), clamp_to_dtype(rec.value, "i32") if rec else 0)

    def acknowledge(self) -> bool:
        """Fault reset: refused (counted, False) while a cause persists; else every fault acknowledged (True):
        0x603F and 0x1001 then tell the warnings still active, or, with none, 0x603F = 0 and the EMCY error
        reset goes out."""
        if self.causes:
            self._counters["fault_resets_refused"] += 1
            return False
        self.records = [FaultRecord(f.emcy_code, f.fault_number, f.value, f.text, f.time_s, f.injected, True)
                        for f in self.records]
        self._publish_errors(fault_active=False)
        return True

    def clear_causes(self, name: str) -> None:
        """Every persistent cause named ``name`` gone."""
        for code in [code for code, cause in self.causes.items() if cause == name]:
            del self.causes[code]

    def clear_cause(self, code: int, name: str) -> None:
        """The cause ``name`` of fault ``code`` gone (another cause of that code stays)."""
        if self.causes.get(code) == name:
            del self.causes[code]

    # ------------------------------------------------------------------ warnings
    def set_warning(self, code: int, active: bool, alarm_number: int | None, fault_active: bool) -> bool:
        """Set or clear a warning; returns whether it changed. On activation its EMCY goes out and 0x603F shows
        it; when it goes, 0x603F and 0x1001 tell the errors still active (the faults too while
        ``fault_active``: FAULT or FAULT REACTION ACTIVE), or, with none left, the EMCY error reset."""
        if active:
            if code in self.warnings:
                return False
            info = fault_info(code)
            self.warnings[code] = int(alarm_number if alarm_number is not None else info.fault_number)
            self._store((0x603F, 0), code)
            self._emcy(code, info.register_bits, b"\x00\x00\x00\x00\x00")
        else:
            if self.warnings.pop(code, None) is None:
                return False
            self._publish_errors(fault_active)
        self.update_alarm()
        return True

    def repeat_warning(self, code: int, data: bytes) -> None:
        """The EMCY of an active warning once more, with ``data`` (a set-point refused again)."""
        self._store((0x603F, 0), code)
        self._emcy(code, fault_info(code).register_bits, data)

    def _publish_errors(self, fault_active: bool) -> None:
        """After an error went: 0x603F = the newest fault not yet acknowledged (only while ``fault_active``),
        else the newest warning still active, and 0x1001 = the generic bit and the class bits of those errors
        (no EMCY); with no error left, 0x603F = 0 and the EMCY error reset (0x0000)."""
        faults = [rec.emcy_code for rec in self.records if not rec.acknowledged] if fault_active else []
        if not faults and not self.warnings:
            self._store((0x603F, 0), 0)
            self._emcy_reset()
            return
        bits = 0x01
        for code in (*faults, *self.warnings):
            bits |= fault_info(code).register_bits
        self._store((0x603F, 0), faults[0] if faults else next(reversed(self.warnings)))
        self._error_register(bits)

    def update_alarm(self) -> None:
        """0x2031 = the motor-temperature alarm, else the newest warning's alarm number; bit 7 follows."""
        alarm = self.temperature_alarm
        if not alarm and self.warnings:
            alarm = next(reversed(self.warnings.values()))
        self.alarm = alarm
        self.warning = alarm != 0 or bool(self.warnings)
