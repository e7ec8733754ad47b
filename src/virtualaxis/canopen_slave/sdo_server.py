"""SDO server (CiA 301 7.2.4): expedited, segmented, block download and block upload (CRC-16 CCITT).

Protocol framing only: object access (existence, access type, length, limits, application hooks) is done
by the slave's ``sdo_upload`` / ``sdo_download``, which raise :class:`SdoAbort` with the right code.
Frames whose DLC is not 8 are counted as malformed and ignored (as CANopenNode-based drives do); the
client then times out.
"""

from __future__ import annotations

import binascii
import struct
from typing import TYPE_CHECKING

from virtualaxis.canopen_slave import errors as ab
from virtualaxis.canopen_slave.counters import abort_key
from virtualaxis.canopen_slave.errors import SdoAbort

if TYPE_CHECKING:
    from virtualaxis.canopen_slave.context import SdoNode

IDLE, SEG_DOWNLOAD, SEG_UPLOAD, BLOCK_DOWNLOAD, BLOCK_DOWNLOAD_END = 0, 1, 2, 3, 4
BLOCK_UPLOAD_START, BLOCK_UPLOAD_ACK, BLOCK_UPLOAD_END = 5, 6, 7

#: server-side SDO timeout: a transfer that sees no client frame for this long is aborted (0x05040000)
SDO_TIMEOUT_S = 1.0
#: largest object the server accepts by segmented / block download [bytes]
MAX_DOWNLOAD_BYTES = 65536
BLOCK_SIZE = 127

_MUX = struct.Struct("<BHB")


def crc16(data: bytes) -> int:
    """CRC-16-CCITT (polynomial 0x1021, initial 0) as used by SDO block transfer."""
    return binascii.crc_hqx(data, 0)


class SdoServer:
    """The default SDO server channel (0x600 + id -> 0x580 + id)."""

    def __init__(self, slave: SdoNode):
        self.slave = slave
        self.tx_cob = 0x580 + slave.node_id
        self.rx_cob = 0x600 + slave.node_id
        self.last_activity_s = 0.0      # time of the last client frame (kept through reset())
        self.reset()

    def reset(self) -> None:
        self.state = IDLE
        self.index = 0
        self.sub = 0
        self.toggle = 0
        self.buffer = bytearray()
        self.size: int | None = None
        self.position = 0
        self.crc_enabled = False
        self.block_size = BLOCK_SIZE
        self.expected_seq = 1
        self.last_good_seq = 0
        self.block_start = 0
        self.block_segments = 0          # segments sent in the current upload sub-block
        self.block_last_sent = False

    # ------------------------------------------------------------------ framing helpers
    def _send(self, data: bytes | bytearray) -> None:
        self.slave.send(self.tx_cob, data)

    def _reply(self, command: int, payload: bytes = b"\x00\x00\x00\x00") -> None:
        self._send(_MUX.pack(command, self.index, self.sub) + payload)

    def abort(self, code: int, index: int | None = None, sub: int | None = None) -> None:
        """Send an abort frame, count it and return to idle."""
        c = self.slave.counters
        c["sdo_aborts_sent"] += 1
        key = abort_key(code)
        c[key] = c.get(key, 0) + 1
        if code == ab.TOGGLE_BIT:
            c["sdo_toggle_errors"] += 1
        elif code == ab.UNKNOWN_COMMAND:
            c["sdo_unknown_command"] += 1
        elif code == ab.SDO_TIMEOUT:
            c["sdo_timeouts"] += 1
        self._send(_MUX.pack(0x80, self.index if index is None else index, self.sub if sub is None else sub)
                   + struct.pack("<I", code))
        self.reset()

    def check_timeout(self, now_s: float) -> None:
        if self.state != IDLE and now_s - self.last_activity_s > SDO_TIMEOUT_S:
            self.abort(ab.SDO_TIMEOUT)

    # ------------------------------------------------------------------ entry point
    def on_frame(self, data: bytes, now_s: float) -> None:
        slave = self.slave
        if len(data) != 8:
            slave.counters["malformed_frames"] += 1
            return
        slave.counters["sdo_requests"] += 1
        self.last_activity_s = now_s
        b0 = data[0]
        state = self.state
        if state == BLOCK_DOWNLOAD:
            if b0 == 0x80:                     # abort from the client (seq 0 is never a data segment)
                self._client_abort()
            else:
                self._block_download_segment(data)
            return
        ccs = b0 >> 5
        if ccs == 4:
            self._client_abort()
            return
        try:
            if ccs == 1:
                self._initiate_download(data)
            elif ccs == 2:
                self._initiate_upload(data)
            elif ccs == 6 and b0 & 0x01 == 0:
                self._initiate_block_download(data)
            elif ccs == 5 and b0 & 0x03 == 0:
                self._initiate_block_upload(data)
            elif ccs == 0 and state == SEG_DOWNLOAD:
                self._download_segment(data)
            elif ccs == 3 and state == SEG_UPLOAD:
                self._upload_segment(data)
            elif ccs == 6 and state == BLOCK_DOWNLOAD_END:
                self._end_block_download(data)
            elif ccs == 5 and b0 & 0x03 == 3 and state == BLOCK_UPLOAD_START:
                self._send_sub_block()
            elif ccs == 5 and b0 & 0x03 == 2 and state == BLOCK_UPLOAD_ACK:
                self._block_upload_ack(data)
            elif ccs == 5 and b0 & 0x03 == 1 and state == BLOCK_UPLOAD_END:
                self.reset()
            else:
                self.abort(ab.UNKNOWN_COMMAND)
        except SdoAbort as exc:
            self.abort(exc.code)
        except Exception:  # noqa: BLE001 - a stack bug: answered at once (0x08000000), counted, never silent
            slave.counters["internal_errors"] += 1
            self.abort(ab.GENERAL_ERROR)

    def _client_abort(self) -> None:
        self.slave.counters["sdo_aborts_received"] += 1
        self.reset()

    def _set_mux(self, data: bytes) -> None:
        _cmd, self.index, self.sub = _MUX.unpack_from(data)

    # ------------------------------------------------------------------ download
    def _initiate_download(self, data: bytes) -> None:
        self.reset()
        self._set_mux(data)
        b0 = data[0]
        expedited, size_indicated = b0 & 0x02, b0 & 0x01
        if expedited:
            if size_indicated:
                payload = bytes(data[4:8 - ((b0 >> 2) & 0x03)])
            else:
                size = self.slave.entry_size(self.index, self.sub)
                payload = bytes(data[4:4 + size]) if size and size <= 4 else bytes(data[4:8])
            self.slave.sdo_download(self.index, self.sub, payload)
            self._reply(0x60)
            return
        self.slave.sdo_check_writable(self.index, self.sub)
        self.size = struct.unpack_from("<I", data, 4)[0] if size_indicated else None
        if self.size is not None:
            self.slave.sdo_check_length(self.index, self.sub, self.size)
        self.state = SEG_DOWNLOAD
        self._reply(0x60)

    def _download_segment(self, data: bytes) -> None:
        b0 = data[0]
        toggle = (b0 >> 4) & 1
        if toggle != self.toggle:
            self.abort(ab.TOGGLE_BIT)
            return
        self.buffer += data[1:8 - ((b0 >> 1) & 0x07)]
        if len(self.buffer) > MAX_DOWNLOAD_BYTES or (self.size is not None and len(self.buffer) > self.size):
            self.abort(ab.LENGTH_TOO_HIGH)
            return
        last = b0 & 0x01
        if last:
            if self.size is not None and len(self.buffer) != self.size:
                self.abort(ab.LENGTH_MISMATCH)
                return
            self.slave.sdo_download(self.index, self.sub, bytes(self.buffer))
            self._send(bytes((0x20 | (toggle << 4), 0, 0, 0, 0, 0, 0, 0)))
            self.reset()
            return
        self._send(bytes((0x20 | (toggle << 4), 0, 0, 0, 0, 0, 0, 0)))
        self.toggle ^= 1

    def _initiate_block_download(self, data: bytes) -> None:
        self.reset()
        self._set_mux(data)
        b0 = data[0]
        self.crc_enabled = bool(b0 & 0x04)
        self.slave.sdo_check_writable(self.index, self.sub)
        self.size = struct.unpack_from("<I", data, 4)[0] if b0 & 0x02 else None
        if self.size is not None:
            if self.size > MAX_DOWNLOAD_BYTES:
                raise SdoAbort(ab.LENGTH_TOO_HIGH)
            self.slave.sdo_check_length(self.index, self.sub, self.size)
        self.state = BLOCK_DOWNLOAD
        self.expected_seq = 1
        self.last_good_seq = 0
        self._send(_MUX.pack(0xA4, self.index, self.sub) + bytes((self.block_size, 0, 0, 0)))

    def _block_download_segment(self, data: bytes) -> None:
        b0 = data[0]
        seq, last = b0 & 0x7F, b0 & 0x80
        if seq == 0:
            self.abort(ab.INVALID_SEQUENCE)
            return
        accepted = seq == self.expected_seq
        if accepted:
            self.buffer += data[1:8]
            self.last_good_seq = seq
            self.expected_seq += 1
            if len(self.buffer) > MAX_DOWNLOAD_BYTES + 7:
                self.abort(ab.LENGTH_TOO_HIGH)
                return
        if seq >= self.block_size or (last and accepted) or (last and not accepted):
            self._send(bytes((0xA2, self.last_good_seq, self.block_size, 0, 0, 0, 0, 0)))
            self.expected_seq = 1
            self.last_good_seq = 0
            if last and accepted:
                self.state = BLOCK_DOWNLOAD_END

    def _end_block_download(self, data: bytes) -> None:
        b0 = data[0]
        if b0 & 0x01 != 0x01:
            self.abort(ab.UNKNOWN_COMMAND)
            return
        unused = (b0 >> 2) & 0x07
        if unused:
            del self.buffer[len(self.buffer) - unused:]
        if self.crc_enabled and crc16(bytes(self.buffer)) != struct.unpack_from("<H", data, 1)[0]:
            self.abort(ab.CRC_ERROR)
            return
        if self.size is not None and len(self.buffer) != self.size:
            self.abort(ab.LENGTH_MISMATCH)
            return
        self.slave.sdo_download(self.index, self.sub, bytes(self.buffer))
        self._send(bytes((0xA1, 0, 0, 0, 0, 0, 0, 0)))
        self.reset()

    # ------------------------------------------------------------------ upload
    def _initiate_upload(self, data: bytes) -> None:
        self.reset()
        self._set_mux(data)
        self._start_upload(self.slave.sdo_upload(self.index, self.sub))

    def _start_upload(self, payload: bytes) -> None:
        n = len(payload)
        if 0 < n <= 4:
            self._reply(0x43 | ((4 - n) << 2), payload + bytes(4 - n))
            return
        self.buffer = bytearray(payload)
        self.position = 0
        self.toggle = 0
        self.state = SEG_UPLOAD
        self._reply(0x41, struct.pack("<I", n))

    def _upload_segment(self, data: bytes) -> None:
        toggle = (data[0] >> 4) & 1
        if toggle != self.toggle:
            self.abort(ab.TOGGLE_BIT)
            return
        chunk = self.buffer[self.position:self.position + 7]
        self.position += len(chunk)
        last = self.position >= len(self.buffer)
        self._send(bytes(((toggle << 4) | ((7 - len(chunk)) << 1) | (1 if last else 0),)) + chunk
                   + bytes(7 - len(chunk)))
        if last:
            self.reset()
        else:
            self.toggle ^= 1

    def _initiate_block_upload(self, data: bytes) -> None:
        self.reset()
        self._set_mux(data)
        b0 = data[0]
        block_size, switch_threshold = data[4], data[5]
        if block_size == 0 or block_size > 127:
            raise SdoAbort(ab.INVALID_BLOCK_SIZE)
        payload = self.slave.sdo_upload(self.index, self.sub)
        if switch_threshold and len(payload) <= switch_threshold:
            self._start_upload(payload)          # protocol switch to expedited / segmented upload
            return
        self.crc_enabled = bool(b0 & 0x04)
        self.block_size = block_size
        self.buffer = bytearray(payload)
        self.position = 0
        self.state = BLOCK_UPLOAD_START
        self._reply(0xC6, struct.pack("<I", len(payload)))

    def _send_sub_block(self) -> None:
        self.block_start = self.position
        pos = self.position
        total = len(self.buffer)
        sent = 0
        for seq in range(1, self.block_size + 1):
            chunk = self.buffer[pos:pos + 7]
            pos += len(chunk)
            last = pos >= total
            self._send(bytes((seq | (0x80 if last else 0),)) + chunk + bytes(7 - len(chunk)))
            sent = seq
            if last:
                break
        self.block_segments = sent
        self.block_last_sent = pos >= total
        self.state = BLOCK_UPLOAD_ACK

    def _block_upload_ack(self, data: bytes) -> None:
        ack_seq, new_size = data[1], data[2]
        if ack_seq > self.block_segments:
            # the client acknowledges segments that were never sent (CiA 301 7.2.4.3.13: invalid sequence)
            self.abort(ab.INVALID_SEQUENCE)
            return
        if new_size == 0 or new_size > 127:
            self.abort(ab.INVALID_BLOCK_SIZE)
            return
        total = len(self.buffer)
        self.position = min(self.block_start + 7 * ack_seq, total)
        self.block_size = new_size
        if self.position >= total and self.block_last_sent:
            used = total - self.block_start - 7 * (ack_seq - 1) if total else 0
            unused = 7 - used if total else 7
            crc = crc16(bytes(self.buffer)) if self.crc_enabled else 0
            self._send(bytes((0xC1 | (unused << 2),)) + struct.pack("<H", crc) + bytes(5))
            self.state = BLOCK_UPLOAD_END
            return
        self._send_sub_block()
