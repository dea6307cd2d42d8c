"""One ping's echoes as arrays: what a driver source produces and the localiser reads.

Mirrors the ``sonar_ring/Echoes`` message (N echo rows, K receivers per group);
``sonar_ring.ros.convert`` turns one into the other without a per-element loop.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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

    def path_lengths(self) -> np.ndarray:
        """Path lengths ``d = c * tof``, shape (N, K), m (NaN where a receiver missed)."""
        return self.speed_of_sound * self.tof


def sanitize(echoes: EchoArrays, n_groups: int, group_transmitters: np.ndarray, max_tof: float):
    """Keep what is usable of a ping; count what is not, by reason.

    Parameters
    ----------
    echoes : EchoArrays
        A ping as received.
    n_groups : int
        Groups of the layout.
    group_transmitters : ndarray of int, shape (G, M)
        Transmitters each group reports (``Layout.group_transmitters``).
    max_tof : float
        Longest time of flight the sensor can report, s (from its maximum range).

    Returns
    -------
    kept : EchoArrays
        Rows with a known group and transmitter; TOFs that are not finite,
        not positive or longer than ``max_tof`` replaced by NaN (a missed echo);
        rows left without any TOF dropped.
    problems : dict of str to int
        ``unknown_group``, ``unknown_transmitter``, ``not_finite_tof``,
        ``not_positive_tof``, ``tof_too_long``, ``empty_row`` -- counts of
        rows (group, transmitter, empty) or values (TOFs).
    """
    group = np.asarray(echoes.group, dtype=np.int64)
    transmitter = np.asarray(echoes.transmitter, dtype=np.int64)
    known_group = group < n_groups
    allowed = np.zeros(echoes.n_echoes, dtype=bool)
    allowed[known_group] = np.any(group_transmitters[group[known_group]] == transmitter[known_group, None], axis=1)
    tof = np.array(echoes.tof, dtype=float)
    infinite = np.isinf(tof)
    finite = np.isfinite(tof)
    not_positive = finite & (tof <= 0)
    too_long = finite & (tof > max_tof)
    tof[infinite | not_positive | too_long] = np.nan
    heard = np.any(np.isfinite(tof), axis=1)
    keep = known_group & allowed & heard
    problems = {
        "unknown_group": int(np.count_nonzero(~known_group)),
        "unknown_transmitter": int(np.count_nonzero(known_group & ~allowed)),
        "not_finite_tof": int(np.count_nonzero(infinite[known_group & allowed])),
        "not_positive_tof": int(np.count_nonzero(not_positive[known_group & allowed])),
        "tof_too_long": int(np.count_nonzero(too_long[known_group & allowed])),
        "empty_row": int(np.count_nonzero(known_group & allowed & ~heard)),
    }
    kept = EchoArrays(layout=echoes.layout, speed_of_sound=echoes.speed_of_sound, group=echoes.group[keep],
                      transmitter=echoes.transmitter[keep], tof=tof[keep], amplitude=echoes.amplitude[keep],
                      phase_delay=echoes.phase_delay[keep])
    return kept, {reason: n for reason, n in problems.items() if n}
