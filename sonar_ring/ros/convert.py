"""numpy arrays <-> sonar_ring messages, without a copy per element.

rclpy stores primitive sequences as ``array.array``; building one from a numpy
buffer costs well under a microsecond for a ping, where assigning the numpy array
itself makes rclpy check every element (tens of microseconds).  What the nodes
publish on every ping is written straight into its serialized form
(:class:`Cdr`, :func:`serialize_landmarks`): a message object would still be
converted field by field when published.
"""

from __future__ import annotations

import array
import struct

import numpy as np

from sonar_ring.echoes import EchoArrays
from sonar_ring.landmarks import Landmarks, make_landmarks
from sonar_ring.msg import Echoes, Landmark, LandmarkArray

_TYPECODES = {np.float64: "d", np.float32: "f", np.uint8: "B", np.uint16: "H", np.uint32: "I"}


class MessageError(ValueError):
    """A message whose arrays do not fit together; the text says which and how."""


def to_sequence(values, dtype) -> array.array:
    """``values`` as the ``array.array`` rclpy keeps for a sequence of ``dtype``."""
    dtype = np.dtype(dtype).type
    return array.array(_TYPECODES[dtype], np.ascontiguousarray(values, dtype=dtype).tobytes())


def from_sequence(values, dtype) -> np.ndarray:
    """A read-only numpy view of a message sequence (``array.array``), no copy."""
    return np.frombuffer(values, dtype=dtype) if len(values) else np.empty(0, dtype=dtype)


class Cdr:
    """Little-endian CDR (the encoding rmw uses), alignment counted from after the 4-byte encapsulation header."""

    def __init__(self) -> None:
        self.buffer = bytearray(b"\x00\x01\x00\x00")

    def align(self, size: int) -> None:
        """Zero padding up to the next multiple of ``size`` bytes."""
        self.buffer += bytes(-(len(self.buffer) - 4) % size)

    def pack(self, fmt: str, *values, align: int) -> None:
        """``values`` by the :mod:`struct` format ``fmt``, after aligning to ``align`` bytes."""
        self.align(align)
        self.buffer += struct.pack("<" + fmt, *values)

    def string(self, text: str) -> None:
        """A string: its length in bytes with the terminating NUL, then UTF-8 and the NUL."""
        data = text.encode()
        self.pack("I", len(data) + 1, align=4)
        self.buffer += data + b"\x00"

    def header(self, sec: int, nanosec: int, frame_id: str) -> None:
        """A ``std_msgs/Header``: the stamp's seconds and nanoseconds, then the frame."""
        self.pack("iI", sec, nanosec, align=4)
        self.string(frame_id)

    def array(self, values: np.ndarray, align: int) -> None:
        """A sequence: its length in elements (rows of ``values``), then the raw values, aligned when there are any.

        Fast CDR aligns no empty sequence, and its reader expects the next field right after the length.
        """
        self.pack("I", len(values), align=4)
        if len(values):
            self.align(align)
            self.buffer += np.ascontiguousarray(values).tobytes()


LANDMARK_ARRAY_FIELDS = (("landmark_class", np.uint8), ("position", np.float64), ("normal", np.float64),
                         ("bearing", np.float64), ("range", np.float64), ("covariance", np.float64),
                         ("confidence", np.float32), ("segment", np.float64), ("observations", np.uint32),
                         ("group", np.uint16), ("echo", np.uint32), ("valid", np.bool_), ("reason", np.uint8))
"""The sequences of ``sonar_ring/LandmarkArray`` after its header, in order, each with its element type;
each is the :class:`~sonar_ring.landmarks.Landmarks` attribute of the same name, flattened."""


def serialize_landmarks(landmarks: Landmarks, header) -> bytes:
    """A serialized ``sonar_ring/LandmarkArray`` of ``landmarks`` with ``header`` (``std_msgs/Header``).

    The message :func:`landmarks_to_msg` builds, as ``rclpy.serialization.serialize_message``
    writes it (same fields when decoded); publishers take it as it is.
    """
    cdr = Cdr()
    cdr.header(header.stamp.sec, header.stamp.nanosec, header.frame_id)
    for name, dtype in LANDMARK_ARRAY_FIELDS:
        flat = np.asarray(getattr(landmarks, name), dtype=np.dtype(dtype).newbyteorder("<")).reshape(-1)
        cdr.array(flat, flat.itemsize)
    return bytes(cdr.buffer)


def echoes_to_msg(echoes: EchoArrays, header) -> Echoes:
    """Build an Echoes message from arrays; ``header`` is a ``std_msgs/Header``."""
    n, k = echoes.tof.shape
    msg = Echoes(header=header, layout=echoes.layout, speed_of_sound=float(echoes.speed_of_sound),
                 receivers_per_group=k)
    msg.group = to_sequence(echoes.group, np.uint16)
    msg.transmitter = to_sequence(echoes.transmitter, np.uint8)
    msg.tof = to_sequence(echoes.tof, np.float64)
    if echoes.amplitude.size:
        msg.amplitude = to_sequence(echoes.amplitude, np.float32)
    if echoes.phase_delay.size:
        msg.phase_delay = to_sequence(echoes.phase_delay, np.float64)
    return msg


ECHO_SEQUENCE_TYPES = {"group": np.uint16, "transmitter": np.uint8, "tof": np.float64, "amplitude": np.float32,
                       "phase_delay": np.float64}
"""Element type of each sequence of ``sonar_ring/Echoes``, by its :class:`~sonar_ring.echoes.EchoArrays` field."""


def as_message_types(echoes: EchoArrays) -> EchoArrays:
    """``echoes`` with each array in the type of its message field (float32 amplitudes, ...).

    What :func:`echoes_from_msg` gives for ``echoes_to_msg(echoes, header)``, without
    building the message: so a ping handed over in one process is the ping the
    next node would decode.
    """
    return EchoArrays(layout=str(echoes.layout), speed_of_sound=float(echoes.speed_of_sound),
                      **{name: np.asarray(getattr(echoes, name), dtype=dtype)
                         for name, dtype in ECHO_SEQUENCE_TYPES.items()})


def echoes_from_msg(msg: Echoes) -> EchoArrays:
    """Arrays of an Echoes message, checked for consistent lengths.

    Raises :class:`MessageError` when the array lengths do not fit N echoes of K
    receivers (the text gives the lengths found and expected).
    """
    k = int(msg.receivers_per_group)
    group = from_sequence(msg.group, np.uint16)
    n = group.shape[0]
    if k < 2:
        raise MessageError(f"receivers_per_group must be >= 2, got {k}")
    lengths = {"transmitter": (len(msg.transmitter), (n,)), "tof": (len(msg.tof), (n * k,)),
               "amplitude": (len(msg.amplitude), (0, n * k)),
               "phase_delay": (len(msg.phase_delay), (0, n * (k - 1)))}
    for name, (found, allowed) in lengths.items():
        if found not in allowed:
            expected = " or ".join(str(a) for a in allowed)
            raise MessageError(f"{name} has {found} values, expected {expected} for {n} echoes of {k} receivers")
    amplitude = from_sequence(msg.amplitude, np.float32).reshape(n, -1 if len(msg.amplitude) else 0)
    phase = from_sequence(msg.phase_delay, np.float64).reshape(n, -1 if len(msg.phase_delay) else 0)
    return EchoArrays(
        layout=msg.layout,
        speed_of_sound=float(msg.speed_of_sound),
        group=group,
        transmitter=from_sequence(msg.transmitter, np.uint8),
        tof=from_sequence(msg.tof, np.float64).reshape(n, k),
        amplitude=amplitude,
        phase_delay=phase,
    )


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


def landmark_messages(msg: LandmarkArray) -> list[Landmark]:
    """One :class:`sonar_ring.msg.Landmark` per entry of a LandmarkArray, for code that wants objects."""
    arrays = landmarks_from_msg(msg)
    return [
        Landmark(header=msg.header, landmark_class=int(arrays.landmark_class[i]),
                 x=float(arrays.position[i, 0]), y=float(arrays.position[i, 1]),
                 normal_x=float(arrays.normal[i, 0]), normal_y=float(arrays.normal[i, 1]),
                 bearing=float(arrays.bearing[i]), range=float(arrays.range[i]),
                 covariance=arrays.covariance[i].ravel().tolist(), confidence=float(arrays.confidence[i]),
                 segment=arrays.segment[i].ravel().tolist(), observations=int(arrays.observations[i]),
                 group=int(arrays.group[i]), echo=int(arrays.echo[i]), valid=bool(arrays.valid[i]),
                 reason=int(arrays.reason[i]))
        for i in range(len(arrays))
    ]
