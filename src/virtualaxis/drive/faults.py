"""Fault codes (CiA 402 EMCY codes with Siemens-style fault numbers) and the fault buffer.

The buffer mirrors SINAMICS r0945 (fault code), r0947 (fault number) and r0949 (fault value): the
latest 8 faults, newest first. Fault numbers marked "inferred" in :data:`FAULT_TABLE` are reasonable
choices, not documented SINAMICS assignments.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class FaultInfo:
    emcy_code: int
    fault_number: int  # Siemens-style F number (r0947)
    text: str
    register_bits: int  # 0x1001 bits besides bit 0: 1 current, 2 voltage, 3 temperature, 4 communication,
    # 5 device profile, 7 manufacturer
    documented: bool  # False: the fault number is inferred
    # reaction class: "option" = ramp per 0x605E from the ACTUAL motion; "coast" = forced OFF2 (pulses off at
    # once: the drive cannot brake under control, e.g. without a position/speed sensor or with an over-current);
    # "quick" = forced quick-stop ramp 0x6085 (OFF3, e.g. a hardware limit switch / STOP cam)
    reaction: str = "option"


FAULT_TABLE: dict[int, FaultInfo] = {
    f.emcy_code: f
    for f in (
        FaultInfo(0x2310, 30001, "over-current (power unit)", 0x02, True, "coast"),
        FaultInfo(0x3210, 30002, "DC-link over-voltage", 0x04, True),
        FaultInfo(0x3220, 30003, "DC-link under-voltage", 0x04, True),
        FaultInfo(0x4210, 30004, "power unit over-temperature", 0x08, True),
        FaultInfo(0x4310, 7011, "motor over-temperature", 0x08, True),
        FaultInfo(0x7305, 31100, "position sensor (encoder 1) signal fault", 0x80, False, "coast"),
        FaultInfo(0x7320, 31110, "position sensor error", 0x80, False, "coast"),
        FaultInfo(0x6320, 7470, "set-point refused: cannot be planned with the present profile objects", 0x80,
                  False),
        FaultInfo(0x8110, 8700, "CAN overrun (objects lost)", 0x10, False),
        FaultInfo(0x8130, 8700, "life guard / heartbeat error", 0x10, False),
        FaultInfo(0x8140, 8700, "recovered from bus off", 0x10, False),
        FaultInfo(0x8210, 8700, "PDO not processed due to length error", 0x10, False),
        FaultInfo(0x8250, 8702, "RPDO timeout", 0x10, False),
        FaultInfo(0x8100, 8701, "communication: SYNC lost", 0x10, False),
        FaultInfo(0x8131, 8703, "loss of control: NMT stopped / reset communication while enabled", 0x10, False),
        FaultInfo(0x8611, 7452, "following error too high", 0x20, False),
        FaultInfo(0x8612, 7491, "reference limit (software limit) exceeded", 0x20, False),
        FaultInfo(0x5530, 1000, "internal software error", 0x80, False),
        FaultInfo(0x5400, 1620, "safe torque off active (STO input)", 0x80, False, "coast"),
        FaultInfo(0x6100, 1000, "internal software error (exception in the drive cycle)", 0x80, True, "coast"),
        FaultInfo(0x8400, 7900, "braking failed: axis not at standstill after the stop ramp", 0x20, False, "coast"),
        FaultInfo(0x8401, 7901, "motor overspeed (beyond 1.2 x 0x6080 max motor speed)", 0x20, True, "coast"),
        FaultInfo(0x8600, 7493, "position actual value outside the range of the position objects", 0x20, False),
        FaultInfo(0xFF10, 7491, "hardware limit switch minus (STOP cam minus) reached", 0x80, True, "quick"),
        FaultInfo(0xFF11, 7492, "hardware limit switch plus (STOP cam plus) reached", 0x80, True, "quick"),
    )
}

FAULT_BUFFER_LENGTH = 8

#: loss of control (``Drive.communication_error``): kind -> (EMCY code, whether the CANopen stack sent the EMCY)
COMMUNICATION_FAULTS: dict[str, tuple[int, bool]] = {
    "heartbeat_lost": (0x8130, True),
    "life_guarding": (0x8130, True),
    "rpdo_timeout": (0x8250, True),
    "bus_off": (0x8140, True),
    "sync_loss": (0x8100, True),
    "nmt_stopped": (0x8131, False),
    "nmt_reset_communication": (0x8131, False),
}


def fault_info(emcy_code: int) -> FaultInfo:
    """The table entry for a code; unknown codes are accepted as generic manufacturer faults."""
    info = FAULT_TABLE.get(emcy_code)
    if info is not None:
        return info
    return FaultInfo(emcy_code, 1000, f"fault 0x{emcy_code:04X}", 0x80, False)


@dataclass(frozen=True)
class FaultRecord:
    """One entry of the fault buffer."""

    emcy_code: int  # r0945
    fault_number: int  # r0947
    value: int  # r0949: fault value (e.g. following error in position units)
    text: str
    time_s: float  # drive time when raised
    injected: bool  # raised by inject_fault (HIL fault injection)
    acknowledged: bool = False

    def as_dict(self) -> dict:
        return {
            "emcy_code": f"0x{self.emcy_code:04X}",
            "fault_number": f"F{self.fault_number:05d}",
            "value": self.value,
            "text": self.text,
            "time_s": self.time_s,
            "injected": self.injected,
            "acknowledged": self.acknowledged,
        }
