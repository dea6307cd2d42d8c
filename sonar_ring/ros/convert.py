"""numpy arrays <-> sonar_ring messages, without a copy per element.

The pings the nodes take are read straight from their serialized form
(:class:`CdrReader`, :func:`echoes_from_cdr`), and what they publish on every
ping is written straight into it (:class:`Cdr`, :func:`serialize_landmarks`): a
message object is built, or converted, field by field in Python, which costs
little back to back but much more in a process that waited for its ping (its
code and data gone cold).  For code that builds message objects, rclpy stores
primitive sequences as ``array.array``; one is built from a numpy buffer in a
single copy, where assigning the numpy array itself makes rclpy check every
element.  BENCHMARKS.md ("Latency work, step by step") has the figures.
"""

from __future__ import annotations

import array
import struct
from typing import NamedTuple

import numpy as np
from builtin_interfaces.msg import Time
from std_msgs.msg import Header

from sonar_ring.echoes import EchoArrays
from sonar_ring.landmarks import Landmarks, make_landmarks
from sonar_ring.msg import Echoes, LandmarkArray

_TYPECODES = {np.float64: "d", np.float32: "f", np.uint8: "B", np.uint16: "H", np.uint32: "I"}


class MessageError(ValueError):
    """A message whose arrays do not fit together; the text says which and how."""


class Stamp(NamedTuple):
    """A ``builtin_interfaces/Time`` read from a serialized message: seconds and nanoseconds."""

    sec: int
    nanosec: int


class MessageHeader(NamedTuple):
    """A ``std_msgs/Header`` read from a serialized message, read as the message is (``header.stamp.sec``).

    The nodes only check and copy a ping's header before its markers are out,
    and building the message object would cost more than that in a process
    that waited for its ping.  :func:`header_message` builds it for typed publishers.
    """

    stamp: Stamp
    frame_id: str


AnyHeader = Header | MessageHeader
"""A header as the nodes pass it on: a message's, or one read from a serialized message; read alike."""


def header_message(header: AnyHeader) -> Header:
    """``header`` (a ``std_msgs/Header`` or a :class:`MessageHeader`) as a ``std_msgs/Header`` message."""
    if isinstance(header, Header):
        return header
    return Header(stamp=Time(sec=header.stamp.sec, nanosec=header.stamp.nanosec), frame_id=header.frame_id)


def to_sequence(values, dtype) -> array.array:
    """``values`` as the ``array.array`` rclpy keeps for a sequence of ``dtype``."""
    dtype = np.dtype(dtype).type
    return array.array(_TYPECODES[dtype], np.ascontiguousarray(values, dtype=dtype).tobytes())


def from_sequence(values, dtype) -> np.ndarray:
    """A numpy view of a message sequence (``array.array``: writable, the message's own memory), no copy."""
    return np.frombuffer(values, dtype=dtype) if len(values) else np.empty(0, dtype=dtype)


class Cdr:
    """Little-endian CDR (the encoding rmw uses), alignment counted from after the 4-byte encapsulation header."""

    def __init__(self) -> None:
        self.buffer = bytearray(b"\x00\x01\x00\x00")

    def align(self, size: int) -> None:
        """Zero padding up to the next multiple of ``size`` bytes."""
        self.buffer += _PADDING[-(len(self.buffer) - 4) % size]

    # The methods below pad inline rather than call align(): a ping's markers and landmarks take
    # about seventy of these calls, each costing more than its work in a process that waited for the ping.

    def pack(self, fmt: str, *values, align: int) -> None:
        """``values`` by the :mod:`struct` format ``fmt`` (little-endian), after aligning to ``align`` bytes."""
        buffer = self.buffer
        buffer += _PADDING[-(len(buffer) - 4) % align]
        buffer += struct.pack("<" + fmt, *values)

    def string(self, text: str) -> None:
        """A string: its length in bytes with the terminating NUL, then UTF-8 and the NUL."""
        data = text.encode()
        buffer = self.buffer
        buffer += _PADDING[-(len(buffer) - 4) % 4]
        buffer += _UINT32.pack(len(data) + 1)
        buffer += data
        buffer += b"\x00"

    def header(self, sec: int, nanosec: int, frame_id: str) -> None:
        """A ``std_msgs/Header``: the stamp's seconds and nanoseconds, then the frame."""
        self.pack("iI", sec, nanosec, align=4)
        self.string(frame_id)

    def array(self, values: np.ndarray, align: int) -> None:
        """A sequence: its length in elements (rows of ``values``), then the raw values, aligned when there are any.

        Fast CDR aligns no empty sequence, and its reader expects the next field right after the length.
        """
        buffer = self.buffer
        buffer += _PADDING[-(len(buffer) - 4) % 4]
        buffer += _UINT32.pack(len(values))
        if len(values):
            buffer += _PADDING[-(len(buffer) - 4) % align]
            buffer += np.ascontiguousarray(values).tobytes()


_PADDING = tuple(bytes(size) for size in range(8))
"""Zero bytes to pad with, by count (CDR aligns to at most 8)."""
_UINT32 = struct.Struct("<I")


class CdrReader:
    """Reads CDR as :class:`Cdr` writes it (little- or big-endian), from the start of a serialized message.

    Every read checks that the bytes are there: a message cut short or with a
    length that runs past its end raises :class:`MessageError`, naming ``what``.
    """

    _ENCAPSULATIONS = {b"\x00\x01": "<", b"\x00\x00": ">"}

    def __init__(self, data: bytes, what: str) -> None:
        self.data, self.what, self.offset = data, what, 4
        self.order = self._ENCAPSULATIONS.get(bytes(data[:2]))
        if self.order is None or len(data) < 4:
            raise MessageError(f"{what}: not plain CDR (encapsulation {bytes(data[:4])!r})")

    def unpack(self, fmt: str, align: int) -> tuple:
        """Values by the :mod:`struct` format ``fmt``, after aligning to ``align`` bytes."""
        self.offset += -(self.offset - 4) % align  # inline, as in Cdr: a ping's message takes about ten
        fmt = self.order + fmt
        try:
            values = struct.unpack_from(fmt, self.data, self.offset)
        except struct.error:
            raise MessageError(f"{self.what}: ends at byte {len(self.data)}, inside a field at {self.offset}") from None
        self.offset += struct.calcsize(fmt)
        return values

    def string(self) -> str:
        """A string: its length with the NUL, the UTF-8 bytes and the NUL; cut at a NUL inside, as rclpy does."""
        (size,) = self.unpack("I", align=4)
        end = self.offset + size
        if size == 0 or end > len(self.data) or self.data[end - 1] != 0:
            raise MessageError(f"{self.what}: a string of {size} bytes at {self.offset} runs past the end "
                               "or lacks its NUL")
        try:
            text = bytes(self.data[self.offset:end - 1]).split(b"\x00", 1)[0].decode()
        except UnicodeDecodeError as error:
            raise MessageError(f"{self.what}: a string at {self.offset} is not UTF-8 ({error})") from None
        self.offset = end
        return text

    def header(self) -> MessageHeader:
        """A ``std_msgs/Header``, as a :class:`MessageHeader`."""
        sec, nanosec = self.unpack("iI", align=4)
        return MessageHeader(Stamp(sec, nanosec), self.string())

    def array(self, dtype) -> np.ndarray:
        """A sequence of ``dtype`` as a native-endian, aligned, writable array of its own."""
        (count,) = self.unpack("I", align=4)
        dtype = np.dtype(dtype)
        if count:
            self.offset += -(self.offset - 4) % dtype.itemsize
        if count * dtype.itemsize > len(self.data) - self.offset:
            raise MessageError(f"{self.what}: a sequence of {count} values at {self.offset} runs past the end "
                               f"({len(self.data)} bytes)")
        values = np.frombuffer(self.data, dtype.newbyteorder(self.order), count, self.offset).astype(dtype)
        self.offset += count * dtype.itemsize
        return values


LANDMARK_ARRAY_FIELDS = (("landmark_class", np.uint8), ("position", np.float64), ("normal", np.float64),
                         ("bearing", np.float64), ("range", np.float64), ("covariance", np.float64),
                         ("confidence", np.float32), ("segment", np.float64), ("observations", np.uint32),
                         ("group", np.uint16), ("echo", np.uint32), ("valid", np.bool_), ("reason", np.uint8))
"""The sequences of ``sonar_ring/LandmarkArray`` after its header, in order, each with its element type;
each is the :class:`~sonar_ring.landmarks.Landmarks` attribute of the same name, flattened."""


def serialize_landmarks(landmarks: Landmarks, header) -> bytes:
    """A serialized ``sonar_ring/LandmarkArray`` of ``landmarks`` with ``header`` (:data:`AnyHeader`).

    The message :func:`landmarks_to_msg` builds, as ``rclpy.serialization.serialize_message``
    writes it (same fields when decoded); publishers take it as it is.
    """
    cdr = Cdr()
    cdr.header(header.stamp.sec, header.stamp.nanosec, header.frame_id)
    for name, dtype in LANDMARK_ARRAY_FIELDS:
        flat = np.asarray(getattr(landmarks, name), dtype=np.dtype(dtype).newbyteorder("<")).reshape(-1)
        cdr.array(flat, flat.itemsize)
    return bytes(cdr.buffer)


ECHO_SEQUENCES = (("group", np.uint16), ("transmitter", np.uint8), ("tof", np.float64), ("amplitude", np.float32),
                  ("phase_delay", np.float64))
"""The sequences of ``sonar_ring/Echoes``, in order, each with its element type; each is the
:class:`~sonar_ring.echoes.EchoArrays` attribute of the same name, flattened."""


def echoes_to_msg(echoes: EchoArrays, header) -> Echoes:
    """Build an Echoes message from arrays; ``header`` is a ``std_msgs/Header`` or a :class:`MessageHeader`."""
    msg = Echoes(header=header_message(header), layout=echoes.layout, speed_of_sound=float(echoes.speed_of_sound),
                 receivers_per_group=echoes.tof.shape[1])
    for name, dtype in ECHO_SEQUENCES:
        setattr(msg, name, to_sequence(getattr(echoes, name), dtype))
    return msg


def as_message_types(echoes: EchoArrays) -> EchoArrays:
    """``echoes`` with each array in the type of its message field (float32 amplitudes, ...).

    What :func:`echoes_from_cdr` gives for ``echoes_to_msg(echoes, header)`` once
    serialized, without building the message: so a ping handed over in one
    process is the ping the next node would decode -- down to an empty ping's
    amplitudes and phase delays, which a message carries as no columns.
    """
    arrays = {name: np.asarray(getattr(echoes, name), dtype=dtype) for name, dtype in ECHO_SEQUENCES}
    for name in ("amplitude", "phase_delay"):
        if arrays[name].size == 0:
            arrays[name] = arrays[name].reshape(len(arrays["group"]), 0)
    return EchoArrays(layout=str(echoes.layout), speed_of_sound=float(echoes.speed_of_sound), **arrays)


def echoes_from_cdr(data: bytes) -> tuple[MessageHeader, EchoArrays]:
    """The header and arrays of a serialized ``sonar_ring/Echoes`` (as a raw subscription or a bag gives it).

    Raises :class:`MessageError` when the bytes are not a whole message, or when
    its array lengths do not fit N echoes of K receivers (the text gives the
    lengths found and expected).  The arrays have their fields' types (float32
    amplitudes), native byte order, and are writable copies.
    """
    reader = CdrReader(data, "sonar_ring/Echoes")
    header = reader.header()
    layout = reader.string()
    (speed_of_sound,) = reader.unpack("d", align=8)
    (k,) = reader.unpack("B", align=1)
    arrays = {name: reader.array(dtype) for name, dtype in ECHO_SEQUENCES}
    n = len(arrays["group"])
    if k < 2:
        raise MessageError(f"receivers_per_group must be >= 2, got {k}")
    allowed = {"transmitter": (n,), "tof": (n * k,), "amplitude": (0, n * k), "phase_delay": (0, n * (k - 1))}
    for name, lengths in allowed.items():
        if len(arrays[name]) not in lengths:
            expected = " or ".join(str(length) for length in lengths)
            raise MessageError(f"{name} has {len(arrays[name])} values, expected {expected} for {n} echoes of {k} "
                               "receivers")
    arrays["tof"] = arrays["tof"].reshape(n, k)
    for name in ("amplitude", "phase_delay"):
        arrays[name] = arrays[name].reshape(n, -1 if len(arrays[name]) else 0)
    return header, EchoArrays(layout=layout, speed_of_sound=speed_of_sound, **arrays)


def landmarks_to_msg(landmarks: Landmarks, header) -> LandmarkArray:
    """Build a LandmarkArray message from :class:`~sonar_ring.landmarks.Landmarks`."""
    msg = LandmarkArray(header=header)
    for name, dtype in LANDMARK_ARRAY_FIELDS:
        values = getattr(landmarks, name)
        # rclpy keeps bool[] as a list: array.array has no bool type.
        setattr(msg, name, values.tolist() if dtype is np.bool_ else to_sequence(values, dtype))
    return msg


def landmarks_from_msg(msg: LandmarkArray) -> Landmarks:
    """:class:`~sonar_ring.landmarks.Landmarks` of a LandmarkArray message.

    Raises :class:`MessageError` when an array's length does not fit the number
    of landmarks given by ``landmark_class``.
    """
    count = len(msg.landmark_class)
    per_landmark = {"position": 2, "normal": 2, "covariance": 4, "confidence": 1, "segment": 4,
                    "observations": 1, "group": 1, "echo": 1, "valid": 1, "reason": 1}
    for name, width in per_landmark.items():
        found = len(getattr(msg, name))
        if found != width * count:
            raise MessageError(f"{name} has {found} values, expected {width * count} for {count} landmarks")
    return make_landmarks(
        from_sequence(msg.landmark_class, np.uint8),
        from_sequence(msg.position, np.float64).reshape(count, 2),
        normal=from_sequence(msg.normal, np.float64).reshape(count, 2),
        covariance=from_sequence(msg.covariance, np.float64).reshape(count, 2, 2),
        confidence=from_sequence(msg.confidence, np.float32),
        segment=from_sequence(msg.segment, np.float64).reshape(count, 2, 2),
        observations=from_sequence(msg.observations, np.uint32),
        group=from_sequence(msg.group, np.uint16),
        echo=from_sequence(msg.echo, np.uint32),
        valid=np.asarray(msg.valid, dtype=bool),
        reason=from_sequence(msg.reason, np.uint8),
    )

