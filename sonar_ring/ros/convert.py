"""numpy arrays <-> sonar_ring messages, without a copy per element.

rclpy stores primitive sequences as ``array.array``; building one from a numpy
buffer costs well under a microsecond for a ping, where assigning the numpy array
itself makes rclpy check every element (tens of microseconds).
"""

from __future__ import annotations

import array
from dataclasses import dataclass

import numpy as np

from sonar_ring.msg import Echoes

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


@dataclass(frozen=True)
class EchoArrays:
    """The arrays of one :class:`sonar_ring.msg.Echoes` ping, N echoes and K receivers.

    Attributes
    ----------
    layout : str
        Layout name the indices refer to.
    speed_of_sound : float
        m/s.
    group, transmitter : ndarray of int, shape (N,)
        Receiver group and transmitter of each echo.
    tof : ndarray, shape (N, K)
        Times of flight, s; NaN where a receiver missed the echo.
    amplitude : ndarray, shape (N, K) or (N, 0)
        Amplitudes relative to A_max, or no columns when not measured.
    phase_delay : ndarray, shape (N, K - 1) or (N, 0)
        Triad phase delays after receiver 0, s, or no columns.
    """

    layout: str
    speed_of_sound: float
    group: np.ndarray
    transmitter: np.ndarray
    tof: np.ndarray
    amplitude: np.ndarray
    phase_delay: np.ndarray

    @property
    def n_echoes(self) -> int:
        """Number of echo rows N."""
        return int(self.group.shape[0])


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
