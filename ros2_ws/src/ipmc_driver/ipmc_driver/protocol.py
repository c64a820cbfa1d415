"""RS-485 frame protocol between the PC and the IPMC rig controller (TMS320F28335).

This is the one module that knows the frame layout: sync bytes, message types, sequence numbers,
lengths, payload layouts and scalings, and the CRC. A lab whose firmware differs changes this
file only. ``docs/protocol.md`` describes the same layout for firmware authors.

Frame (all multi-byte fields little-endian)::

    offset  size  field
    0       2     sync 0xAA 0x55
    2       1     message type
    3       1     sequence number (per sender, wraps 255 -> 0)
    4       1     payload length N (fixed per type)
    5       N     payload
    5+N     2     CRC-16/MODBUS over bytes 2 .. 4+N (type, seq, length, payload)

Pure core: no ROS imports. Codecs raise ``ProtocolError`` / ``ChecksumError``; they neither log
nor exit.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

__all__ = [
    "SYNC",
    "HEADER_LEN",
    "CRC_LEN",
    "MSG_SET_VOLTAGE",
    "MSG_SAMPLE",
    "MSG_STATUS",
    "MSG_PING",
    "MSG_ERROR",
    "PAYLOAD_LENGTHS",
    "SAMPLE_FRAME_LEN",
    "FLAG_LASER_NO_TARGET",
    "FLAG_VOLTAGE_CLAMPED",
    "LASER_MIN_MM",
    "LASER_MAX_MM",
    "LASER_NO_TARGET",
    "ERROR_BAD_FRAME",
    "ERROR_UNKNOWN_TYPE",
    "ERROR_VOLTAGE_LIMIT",
    "RIG_WATCHDOG_S",
    "ProtocolError",
    "ChecksumError",
    "Frame",
    "SetVoltage",
    "Sample",
    "Status",
    "Ping",
    "RigError",
    "DecoderStats",
    "FrameDecoder",
    "crc16_modbus",
    "encode_frame",
    "decode_frame",
    "encode_message",
    "parse_frame",
    "frame_length",
    "laser_mm_to_counts",
    "laser_counts_to_mm",
    "volts_to_millivolts",
]

# --------------------------------------------------------------------------- layout constants
SYNC = b"\xaa\x55"
HEADER_LEN = 5  # sync(2) + type(1) + seq(1) + length(1)
CRC_LEN = 2

MSG_SET_VOLTAGE = 0x01  # PC -> rig
MSG_SAMPLE = 0x02  # rig -> PC, one per sampling period
MSG_STATUS = 0x03  # rig -> PC, heartbeat (1 Hz) and reply to PING
MSG_PING = 0x04  # PC -> rig, asks for a STATUS
MSG_ERROR = 0x7F  # rig -> PC

_SET_VOLTAGE = struct.Struct("<h")  # setpoint, mV
_SAMPLE = struct.Struct("<IhHBB")  # counter, applied mV, laser counts, command seq, flags
_STATUS = struct.Struct("<IHhB")  # counter, sample rate Hz, setpoint mV, flags
_PING = struct.Struct("<")
_ERROR = struct.Struct("<BH")  # code, detail

PAYLOAD_LENGTHS: dict[int, int] = {
    MSG_SET_VOLTAGE: _SET_VOLTAGE.size,
    MSG_SAMPLE: _SAMPLE.size,
    MSG_STATUS: _STATUS.size,
    MSG_PING: _PING.size,
    MSG_ERROR: _ERROR.size,
}

# SAMPLE / STATUS flags
FLAG_LASER_NO_TARGET = 0x01  # the laser spot missed the actuator (sensor reports no target)
FLAG_VOLTAGE_CLAMPED = 0x02  # the firmware limited the setpoint

# Laser reading (LE250, measuring range 100-400 mm) as 16-bit ADC counts; 0xFFFF = no target.
LASER_MIN_MM = 100.0
LASER_MAX_MM = 400.0
LASER_NO_TARGET = 0xFFFF
_LASER_FULL_SCALE = 0xFFFE
_MM_PER_COUNT = (LASER_MAX_MM - LASER_MIN_MM) / _LASER_FULL_SCALE

ERROR_BAD_FRAME = 1  # the rig received a frame with a bad CRC
ERROR_UNKNOWN_TYPE = 2  # the rig received a frame of a type it does not handle
ERROR_VOLTAGE_LIMIT = 3  # a setpoint beyond the firmware limit was clamped

# Firmware watchdog: the rig sets the H-bridge to 0 V when no SET_VOLTAGE frame with a good CRC
# has arrived for this long. 200 ms lies below the double layer's charging time constant (about
# 0.3 s), so a PC that stops leaves the strip driven for less than one time constant, and spans
# four of the PC's 50 ms keepalive periods, so one or two late frames do not trip it.
RIG_WATCHDOG_S = 0.2


def frame_length(msg_type: int) -> int:
    """Total length in bytes of a frame of ``msg_type`` (header + payload + CRC)."""
    try:
        return HEADER_LEN + PAYLOAD_LENGTHS[msg_type] + CRC_LEN
    except KeyError:
        raise ProtocolError(f"unknown message type 0x{msg_type:02x}") from None


SAMPLE_FRAME_LEN = HEADER_LEN + _SAMPLE.size + CRC_LEN


# --------------------------------------------------------------------------- exceptions
class ProtocolError(ValueError):
    """A frame or message that does not follow the protocol."""


class ChecksumError(ProtocolError):
    """A frame whose CRC-16/MODBUS does not match its content."""


# --------------------------------------------------------------------------- CRC
def _make_crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC_TABLE = _make_crc_table()


def crc16_modbus(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/MODBUS (poly 0x8005 reflected, init 0xFFFF, no final xor) of ``data``.

    The check value of ``b"123456789"`` is ``0x4B37``.
    """
    crc = 0xFFFF
    table = _CRC_TABLE
    for byte in data:
        crc = (crc >> 8) ^ table[(crc ^ byte) & 0xFF]
    return crc


# --------------------------------------------------------------------------- scalings
def volts_to_millivolts(voltage_v: float) -> int:
    """Voltage in V as the signed 16-bit millivolt integer carried in frames (saturating)."""
    if voltage_v != voltage_v:  # NaN
        raise ProtocolError("voltage must be a number, got NaN")
    return max(-32768, min(32767, round(voltage_v * 1000.0)))


def laser_mm_to_counts(x_mm: float | None) -> int:
    """Laser reading (mm) as 16-bit ADC counts; ``None`` or out of range -> ``LASER_NO_TARGET``."""
    if x_mm is None or not (LASER_MIN_MM <= x_mm <= LASER_MAX_MM):
        return LASER_NO_TARGET
    return min(_LASER_FULL_SCALE, round((x_mm - LASER_MIN_MM) / _MM_PER_COUNT))


def laser_counts_to_mm(counts: int) -> float | None:
    """16-bit ADC counts as a laser reading in mm; ``LASER_NO_TARGET`` -> ``None``."""
    if counts == LASER_NO_TARGET:
        return None
    return LASER_MIN_MM + counts * _MM_PER_COUNT


# --------------------------------------------------------------------------- frames
@dataclass(frozen=True)
class Frame:
    """One checked frame: message type, sequence number and raw payload."""

    msg_type: int
    seq: int
    payload: bytes


def encode_frame(msg_type: int, seq: int, payload: bytes = b"") -> bytes:
    """Build the bytes of one frame (sync, header, payload, CRC).

    Raises ``ProtocolError`` for an unknown type, a sequence number outside 0-255 or a payload
    whose length is not the one fixed for the type.
    """
    expected = PAYLOAD_LENGTHS.get(msg_type)
    if expected is None:
        raise ProtocolError(f"unknown message type 0x{msg_type:02x}")
    if not 0 <= seq <= 0xFF:
        raise ProtocolError(f"sequence number must be in 0..255, got {seq}")
    if len(payload) != expected:
        raise ProtocolError(
            f"payload of type 0x{msg_type:02x} must be {expected} bytes, got {len(payload)}"
        )
    body = bytes((msg_type, seq, len(payload))) + bytes(payload)
    return SYNC + body + crc16_modbus(body).to_bytes(2, "little")


def decode_frame(data: bytes | bytearray) -> Frame:
    """Check and split exactly one frame.

    Raises ``ChecksumError`` when the CRC does not match and ``ProtocolError`` for any other
    defect (sync, type, length).
    """
    data = bytes(data)
    if len(data) < HEADER_LEN + CRC_LEN:
        raise ProtocolError(f"frame too short: {len(data)} bytes")
    if data[:2] != SYNC:
        raise ProtocolError(f"bad sync bytes {data[:2].hex()}, expected {SYNC.hex()}")
    msg_type, seq, length = data[2], data[3], data[4]
    expected = PAYLOAD_LENGTHS.get(msg_type)
    if expected is None:
        raise ProtocolError(f"unknown message type 0x{msg_type:02x}")
    if length != expected:
        raise ProtocolError(
            f"length field {length} does not match type 0x{msg_type:02x} ({expected})"
        )
    if len(data) != HEADER_LEN + length + CRC_LEN:
        raise ProtocolError(
            f"frame is {len(data)} bytes, header announces {HEADER_LEN + length + CRC_LEN}"
        )
    crc_rx = int.from_bytes(data[-2:], "little")
    crc = crc16_modbus(data[2:-2])
    if crc != crc_rx:
        raise ChecksumError(f"CRC mismatch: frame carries 0x{crc_rx:04x}, computed 0x{crc:04x}")
    return Frame(msg_type, seq, data[HEADER_LEN:-2])


# --------------------------------------------------------------------------- messages
@dataclass(frozen=True)
class SetVoltage:
    """PC -> rig: new H-bridge setpoint, V (1 mV resolution)."""

    voltage_v: float


@dataclass(frozen=True)
class Sample:
    """Rig -> PC: one sampling instant.

    Attributes
    ----------
    counter : int
        Sample counter of the rig (u32), +1 per sampling period since the firmware started.
    applied_v : float
        Voltage applied by the H-bridge at this instant, V.
    laser_mm : float or None
        Raw laser reading x in mm (before arc compensation); ``None`` when the sensor has no
        target.
    command_seq : int
        Sequence number of the last SET_VOLTAGE frame the rig applied.
    flags : int
        ``FLAG_*`` bits.
    """

    counter: int
    applied_v: float
    laser_mm: float | None
    command_seq: int = 0
    flags: int = 0


@dataclass(frozen=True)
class Status:
    """Rig -> PC heartbeat: sample counter, sample rate (Hz), current setpoint (V), flags."""

    counter: int
    sample_rate_hz: int
    setpoint_v: float
    flags: int = 0


@dataclass(frozen=True)
class Ping:
    """PC -> rig: request a STATUS frame."""


@dataclass(frozen=True)
class RigError:
    """Rig -> PC: an error report (``ERROR_*`` code and a code-specific detail)."""

    code: int
    detail: int = 0


Message = SetVoltage | Sample | Status | Ping | RigError


def encode_message(message: Message, seq: int) -> bytes:
    """Encode a message object as one frame with sequence number ``seq``."""
    try:
        if isinstance(message, SetVoltage):
            return encode_frame(
                MSG_SET_VOLTAGE, seq, _SET_VOLTAGE.pack(volts_to_millivolts(message.voltage_v))
            )
        if isinstance(message, Sample):
            payload = _SAMPLE.pack(
                message.counter & 0xFFFFFFFF,
                volts_to_millivolts(message.applied_v),
                laser_mm_to_counts(message.laser_mm),
                message.command_seq & 0xFF,
                message.flags & 0xFF,
            )
            return encode_frame(MSG_SAMPLE, seq, payload)
        if isinstance(message, Status):
            payload = _STATUS.pack(
                message.counter & 0xFFFFFFFF,
                message.sample_rate_hz,
                volts_to_millivolts(message.setpoint_v),
                message.flags & 0xFF,
            )
            return encode_frame(MSG_STATUS, seq, payload)
        if isinstance(message, Ping):
            return encode_frame(MSG_PING, seq, b"")
        if isinstance(message, RigError):
            return encode_frame(MSG_ERROR, seq, _ERROR.pack(message.code, message.detail))
    except struct.error as exc:
        raise ProtocolError(f"cannot encode {message!r}: {exc}") from None
    raise ProtocolError(f"not a protocol message: {message!r}")


def parse_frame(frame: Frame) -> Message:
    """Turn a checked ``Frame`` into its message object (``ProtocolError`` if it cannot)."""
    expected = PAYLOAD_LENGTHS.get(frame.msg_type)
    if expected is None:
        raise ProtocolError(f"unknown message type 0x{frame.msg_type:02x}")
    if len(frame.payload) != expected:
        raise ProtocolError(
            f"payload of type 0x{frame.msg_type:02x} must be {expected} bytes, "
            f"got {len(frame.payload)}"
        )
    if frame.msg_type == MSG_SAMPLE:
        counter, mv, counts, cmd_seq, flags = _SAMPLE.unpack(frame.payload)
        return Sample(counter, mv / 1000.0, laser_counts_to_mm(counts), cmd_seq, flags)
    if frame.msg_type == MSG_SET_VOLTAGE:
        (mv,) = _SET_VOLTAGE.unpack(frame.payload)
        return SetVoltage(mv / 1000.0)
    if frame.msg_type == MSG_STATUS:
        counter, rate, mv, flags = _STATUS.unpack(frame.payload)
        return Status(counter, rate, mv / 1000.0, flags)
    if frame.msg_type == MSG_PING:
        return Ping()
    code, detail = _ERROR.unpack(frame.payload)
    return RigError(code, detail)


# --------------------------------------------------------------------------- streaming decoder
@dataclass
class DecoderStats:
    """Counters of a ``FrameDecoder``.

    Attributes
    ----------
    frames_ok : int
        Frames whose CRC matched.
    bad_crc : int
        Complete frames whose CRC did not match.
    truncated : int
        Partial frames: a frame cut short, recognised because the next frame start (sync, known
        type, matching length) lies inside the span its header announced, or left pending by
        ``reset``. A failed frame with no frame start inside its span counts as ``bad_crc``.
    resyncs : int
        Times the decoder had to discard bytes before finding the next good frame.
    discarded_bytes : int
        Bytes that were not part of any good frame (garbage, bad and partial frames).
    """

    frames_ok: int = 0
    bad_crc: int = 0
    truncated: int = 0
    resyncs: int = 0
    discarded_bytes: int = 0

    def as_dict(self) -> dict[str, int]:
        return {
            "frames_ok": self.frames_ok,
            "bad_crc": self.bad_crc,
            "truncated": self.truncated,
            "resyncs": self.resyncs,
            "discarded_bytes": self.discarded_bytes,
        }


@dataclass
class FrameDecoder:
    """Streaming frame decoder that resynchronises after garbage, partial frames and bad CRCs.

    Feed it bytes as they arrive in chunks of any size; it returns the good frames in order.
    A candidate frame (sync + known type + matching length) whose CRC fails is abandoned one byte
    after its start, so a good frame hidden inside a partial one is still found.

    Examples
    --------
    >>> dec = FrameDecoder()
    >>> frames = dec.feed(b"junk" + encode_message(Ping(), seq=7))
    >>> frames[0].seq, dec.stats.resyncs
    (7, 1)
    """

    stats: DecoderStats = field(default_factory=DecoderStats)
    _buf: bytearray = field(default_factory=bytearray, repr=False)
    _base: int = field(default=0, repr=False)  # stream offset of _buf[0]
    _pending_end: int | None = field(default=None, repr=False)  # end of a failed candidate
    _lost: bool = field(default=False, repr=False)  # bytes discarded since the last good frame

    def feed(self, data: bytes | bytearray | memoryview) -> list[Frame]:
        """Append ``data`` to the stream and return the good frames it completes."""
        buf = self._buf
        buf += data
        out: list[Frame] = []
        stats = self.stats
        pos = 0
        n = len(buf)
        while True:
            i = buf.find(SYNC, pos)
            if i < 0:
                keep = 1 if n > pos and buf[n - 1] == SYNC[0] else 0
                self._discard(n - keep - pos)
                pos = n - keep
                break
            if i > pos:
                self._discard(i - pos)
                pos = i
            self._settle_pending(self._base + pos)
            if n - pos < HEADER_LEN:
                break
            msg_type, length = buf[pos + 2], buf[pos + 4]
            if PAYLOAD_LENGTHS.get(msg_type) != length:
                # Sync bytes inside garbage or a payload: not a frame start.
                self._discard(1)
                pos += 1
                continue
            end = pos + HEADER_LEN + length + CRC_LEN
            if n < end:
                break
            crc_rx = buf[end - 2] | (buf[end - 1] << 8)
            if crc16_modbus(memoryview(buf)[pos + 2 : end - 2]) != crc_rx:
                if self._pending_end is not None:
                    # A plausible frame start inside the span of an earlier failed candidate:
                    # that one was cut short.
                    stats.truncated += 1
                self._pending_end = self._base + end
                self._discard(1)
                pos += 1
                continue
            if self._pending_end is not None:
                # A good frame starts inside the span the failed candidate announced.
                stats.truncated += 1
                self._pending_end = None
            if self._lost:
                stats.resyncs += 1
                self._lost = False
            stats.frames_ok += 1
            out.append(Frame(msg_type, buf[pos + 3], bytes(buf[pos + HEADER_LEN : end - 2])))
            pos = end
        self._settle_pending(self._base + pos)
        if pos:
            del buf[:pos]
            self._base += pos
        return out

    def reset(self) -> None:
        """Forget buffered bytes (e.g. after reconnecting); a pending partial frame is counted."""
        if self._pending_end is not None or self._buf.startswith(SYNC):
            self.stats.truncated += 1
        self._discard(len(self._buf))
        self._base += len(self._buf)
        self._buf.clear()
        self._pending_end = None

    @property
    def buffered(self) -> int:
        """Bytes held while waiting for the rest of a frame."""
        return len(self._buf)

    def _discard(self, count: int) -> None:
        if count > 0:
            self.stats.discarded_bytes += count
            self._lost = True

    def _settle_pending(self, abs_pos: int) -> None:
        # The scan passed the end of a failed candidate without a good frame inside it: the
        # candidate was a whole frame with a bad CRC.
        if self._pending_end is not None and abs_pos >= self._pending_end:
            self.stats.bad_crc += 1
            self._pending_end = None
