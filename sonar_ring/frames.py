"""The binary frame the ring electronics send, version 1: encode, and decode a byte stream.

Firmware sends one frame per ping over serial, UDP (one frame per datagram) or
TCP.  All integers are little-endian; byte ranges are inclusive.  The README's
"Hardware frame" section is the same specification, with an example frame, and
``firmware/sonar_ring_frame.h`` the same encoder in C.

=========  ======  =============================================================
bytes      type    field
=========  ======  =============================================================
0-1        2 B     magic ``0xA5 0x5A``
2          u8      version (1)
3          u8      frame type (1 = echoes)
4-5        u16     payload length P in bytes
6          u8      header check: 255 - (byte 2 + byte 3 + byte 4 + byte 5) mod 256
7..6+P     P B     payload
7+P..10+P  u32     CRC-32 (zlib / IEEE 802.3) of bytes 0 .. 6 + P
=========  ======  =============================================================

Echoes payload (type 1), offsets from its start:

=========  ======  =============================================================
0-3        u32     ping sequence number: the previous ping's plus one, from
                   2**32 - 1 on to 0 (a gap is frames lost)
4-11       u64     device time, µs, when this ping's transmitter fired (the
                   instant its TOFs count from): the device's own clock, any
                   epoch, never going back while it runs, within 1000 ppm of
                   true rate; 0 when the device has no clock (stamped on arrival)
12-13      u16     N, echo rows
14         u8      K, receivers per group
15         u8      flags: bit 0 amplitudes present, bit 1 phase delays present
16-19      u32     speed of sound used by the device, mm/s (0: let the host decide)
20..       N rows  per row: u16 group, u8 transmitter, K x u32 TOF in ns
                   (``0xFFFFFFFF``: this receiver missed the echo), then if
                   flagged K x u16 amplitude ``round(65535 * A / A_max)``,
                   A / A_max clipped to 0..1 and 0 for a receiver that missed
                   (decoded as NaN), then if flagged (K - 1) x i32 phase delay
                   of receivers 1..K-1 after receiver 0, ns
=========  ======  =============================================================

Rows may come in any order, except that the rows of one group after one
transmitter come in the order their echoes arrived: a transducer pair's echoes
after its two transmitters are matched by that order.

The header check lets the decoder reject a corrupted length at once instead of
waiting for up to 64 KiB that belong to the following frames.  The decoder never
raises on bad bytes: it skips to the next magic, counts what it threw away by
reason, and resynchronises on the next good frame.
"""

from __future__ import annotations

import struct
import zlib
from collections import Counter, deque
from dataclasses import dataclass

import numpy as np

from sonar_ring.echoes import EchoArrays

MAGIC = b"\xa5\x5a"
VERSION = 1
TYPE_ECHOES = 1
FLAG_AMPLITUDE = 0x01
FLAG_PHASE = 0x02
MAX_PAYLOAD = 65535
NO_ECHO = 0xFFFFFFFF
SEQUENCE_MODULUS = 2**32
LATE_WINDOW = 16
"""Frames behind the newest that :class:`FrameSequence` takes for late (reordered) rather than a restart."""

_HEADER = struct.Struct("<2sBBHB")
_PING = struct.Struct("<IQHBBI")
_CRC = struct.Struct("<I")


class FrameError(ValueError):
    """An echo set that cannot be put into a frame (the text says why)."""


@dataclass(frozen=True)
class EchoFrame:
    """One decoded echoes frame.

    Attributes
    ----------
    sequence : int
        Ping sequence number from the device.
    device_time_us : int
        Device clock at the ping, microseconds.
    speed_of_sound : float
        m/s the device used, or 0.0 when it leaves that to the host.
    echoes : EchoArrays
        The ping's echoes (``layout`` is empty: the driver knows its layout).
    """

    sequence: int
    device_time_us: int
    speed_of_sound: float
    echoes: EchoArrays


def _row_dtype(k: int, amplitude: bool, phase: bool) -> np.dtype:
    fields = [("group", "<u2"), ("transmitter", "u1"), ("tof", "<u4", (k,))]
    if amplitude:
        fields.append(("amplitude", "<u2", (k,)))
    if phase:
        fields.append(("phase", "<i4", (k - 1,)))
    return np.dtype(fields)


def encode_echoes(echoes: EchoArrays, sequence: int = 0, device_time_us: int = 0) -> bytes:
    """One version-1 echoes frame for ``echoes``; TOF and phase delays rounded to whole ns.

    The amplitude of a receiver that missed the echo (NaN TOF), or that is not
    finite, goes out as 0.  Raises :class:`FrameError` if the ping does not fit
    a frame (payload over 65535 bytes, a TOF over 4.29 s or negative, a group
    over 65535).
    """
    n, k = echoes.tof.shape
    amplitude = echoes.amplitude.shape[1] > 0
    phase = echoes.phase_delay.shape[1] > 0
    rows = np.zeros(n, dtype=_row_dtype(k, amplitude, phase))
    rows["group"] = echoes.group
    rows["transmitter"] = echoes.transmitter
    tof_ns = np.round(np.asarray(echoes.tof, dtype=float) * 1e9)
    missing = ~np.isfinite(tof_ns)
    if np.any(tof_ns[~missing] < 0) or np.any(tof_ns[~missing] >= NO_ECHO):
        raise FrameError("TOF must be in [0, 4.29) s to fit a frame")
    rows["tof"] = np.where(missing, NO_ECHO, np.nan_to_num(tof_ns)).astype(np.uint32)
    if amplitude:
        relative = np.where(missing | ~np.isfinite(echoes.amplitude), 0.0, np.clip(echoes.amplitude, 0.0, 1.0))
        rows["amplitude"] = np.round(relative * 65535).astype(np.uint16)
    if phase:
        rows["phase"] = np.round(echoes.phase_delay * 1e9).astype(np.int32)
    flags = (FLAG_AMPLITUDE if amplitude else 0) | (FLAG_PHASE if phase else 0)
    speed_mm = int(round(echoes.speed_of_sound * 1000)) if echoes.speed_of_sound else 0
    payload = _PING.pack(sequence & 0xFFFFFFFF, device_time_us, n, k, flags, speed_mm) + rows.tobytes()
    if len(payload) > MAX_PAYLOAD:
        raise FrameError(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}: send fewer echoes per frame")
    head = _HEADER.pack(MAGIC, VERSION, TYPE_ECHOES, len(payload), _header_check(VERSION, TYPE_ECHOES, len(payload)))
    head += payload
    return head + _CRC.pack(zlib.crc32(head))


def _header_check(version: int, frame_type: int, length: int) -> int:
    return 255 - (version + frame_type + (length & 0xFF) + (length >> 8)) % 256


def _decode_payload(payload: bytes) -> EchoFrame | str:
    """The frame in ``payload``, or the reason it is malformed."""
    if len(payload) < _PING.size:
        return "short_payload"
    sequence, device_time, n, k, flags, speed_mm = _PING.unpack_from(payload)
    if k < 2:
        return "bad_receiver_count"
    dtype = _row_dtype(k, bool(flags & FLAG_AMPLITUDE), bool(flags & FLAG_PHASE))
    if len(payload) != _PING.size + n * dtype.itemsize:
        return "length_mismatch"
    rows = np.frombuffer(payload, dtype=dtype, offset=_PING.size, count=n)
    missed = rows["tof"] == NO_ECHO
    tof = rows["tof"].astype(float) * 1e-9
    tof[missed] = np.nan
    # Sub-array fields already come out as (N, K) and (N, K - 1).
    if flags & FLAG_AMPLITUDE:
        amplitude = rows["amplitude"].astype(np.float32) / 65535.0
        amplitude[missed] = np.nan
    else:
        amplitude = np.empty((n, 0), np.float32)
    phase = rows["phase"].astype(float) * 1e-9 if flags & FLAG_PHASE else np.empty((n, 0))
    echoes = EchoArrays(layout="", speed_of_sound=speed_mm / 1000.0, group=rows["group"].astype(np.uint16),
                        transmitter=rows["transmitter"].astype(np.uint8), tof=tof,
                        amplitude=amplitude, phase_delay=phase)
    return EchoFrame(sequence, device_time, speed_mm / 1000.0, echoes)


class FrameDecoder:
    """Turns a byte stream into frames, resynchronising after garbage.

    ``feed`` any chunk of bytes (a serial read, a TCP read, a UDP datagram) and
    get the complete frames it finishes.  Bytes that cannot start a valid frame
    are dropped and counted in :attr:`errors` by reason: ``garbage`` (bytes
    before a magic), ``bad_header``, ``bad_version``, ``bad_type``, ``bad_crc``,
    ``truncated`` (a datagram that ended inside a frame), and payload
    problems (``short_payload``, ``bad_receiver_count``, ``length_mismatch``).
    The internal buffer never holds more than one maximum-size frame.
    """

    def __init__(self) -> None:
        self._buffer = bytearray()
        self.errors: Counter[str] = Counter()
        self.frames = 0

    def feed(self, data: bytes) -> list[EchoFrame]:
        """Decode what ``data`` completes; keep an unfinished frame for the next call."""
        self._buffer += data
        frames: list[EchoFrame] = []
        while True:
            start = self._buffer.find(MAGIC)
            if start < 0:
                # Keep a trailing first magic byte: the next chunk may complete it.
                keep = 1 if self._buffer.endswith(MAGIC[:1]) else 0
                self._drop(len(self._buffer) - keep, "garbage")
                return frames
            self._drop(start, "garbage")
            if len(self._buffer) < _HEADER.size:
                return frames
            _, version, frame_type, length, check = _HEADER.unpack_from(self._buffer)
            if check != _header_check(version, frame_type, length):
                self._drop(1, "bad_header")
                continue
            if version != VERSION or frame_type != TYPE_ECHOES:
                self._drop(1, "bad_version" if version != VERSION else "bad_type")
                continue
            total = _HEADER.size + length + _CRC.size
            if len(self._buffer) < total:
                return frames
            frame = bytes(self._buffer[:total])
            (crc,) = _CRC.unpack_from(frame, total - _CRC.size)
            if crc != zlib.crc32(frame[:-_CRC.size]):
                self._drop(1, "bad_crc")
                continue
            decoded = _decode_payload(frame[_HEADER.size:-_CRC.size])
            if isinstance(decoded, str):
                self._drop(1, decoded)
                continue
            del self._buffer[:total]
            self.frames += 1
            frames.append(decoded)

    def feed_datagram(self, data: bytes) -> list[EchoFrame]:
        """Decode one UDP datagram: frames never span datagrams, so leftovers are dropped."""
        frames = self.feed(data)
        if self._buffer:
            self._drop(len(self._buffer), "truncated")
        return frames

    def _drop(self, count: int, reason: str) -> None:
        if count > 0:
            del self._buffer[:count]
            self.errors[reason] += count if reason in ("garbage", "truncated") else 1


class FrameSequence:
    """Where each frame stands in the device's sequence, from its sequence number and device time.

    The device numbers its pings one up each (u32, from ``2**32 - 1`` on to 0)
    and stamps them with its clock, which does not go back while it runs.
    :meth:`place` sorts every frame into one of:

    * ``next`` -- ahead of the newest frame; the numbers skipped are frames lost;
    * ``duplicate`` -- the same number and time as one of the last frames;
    * ``late`` -- behind the newest by fewer than ``window`` numbers, its time
      within theirs: a frame overtaken on the way (UDP), too late to publish;
    * ``device restarted`` -- its time went back: the numbers start afresh, none counted lost;
    * ``sequence restarted`` -- the time went on but the number went back or
      stood still: the numbers start afresh, none counted lost.

    ``next`` and both restarts are frames to publish.
    """

    def __init__(self, window: int = LATE_WINDOW) -> None:
        self._window = window
        self._recent: deque[tuple[int, int]] = deque(maxlen=window)

    def place(self, sequence: int, device_time_us: int) -> tuple[str, int]:
        """The frame's place (one of the class docstring's) and the frames lost just before it."""
        if not self._recent:
            self._recent.append((sequence, device_time_us))
            return "next", 0
        if (sequence, device_time_us) in self._recent:
            return "duplicate", 0
        newest_sequence, newest_time = self._recent[-1]
        behind = (newest_sequence - sequence) % SEQUENCE_MODULUS
        if 0 < behind < self._window and self._recent[0][1] <= device_time_us <= newest_time:
            return "late", 0
        ahead = (sequence - newest_sequence) % SEQUENCE_MODULUS
        if device_time_us >= newest_time and 0 < ahead < SEQUENCE_MODULUS // 2:
            self._recent.append((sequence, device_time_us))
            return "next", ahead - 1
        self._recent.clear()
        self._recent.append((sequence, device_time_us))
        return ("device restarted" if device_time_us < newest_time else "sequence restarted"), 0
