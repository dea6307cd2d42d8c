"""One ping's echoes as arrays: what a driver source produces and the localiser reads.

Mirrors the ``sonar_ring/Echoes`` message (N echo rows, K receivers per group);
``sonar_ring.ros.convert`` turns one into the other without a per-element loop.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

SLOWEST_SPEED_OF_SOUND = 250.0
"""m/s: below any air a robot works in (-50 degC dry air is 299 m/s); slower is a corrupt value."""
FASTEST_SPEED_OF_SOUND = 450.0
"""m/s: above any air a robot works in (+60 degC saturated air is about 375 m/s)."""


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
    known_group = (group >= 0) & (group < n_groups)
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


def longest_tof(layout) -> float:
    """Longest time of flight ``layout``'s receivers can report, s.

    The round trip to ``layout.max_range`` at the slowest plausible speed of
    sound (:data:`SLOWEST_SPEED_OF_SOUND`), with a margin of 25 %.
    """
    return 2.5 * layout.max_range / SLOWEST_SPEED_OF_SOUND


@dataclass(frozen=True)
class Screened:
    """What :func:`screen_ping` kept of a ping and what it threw away.

    Attributes
    ----------
    echoes : EchoArrays or None
        The usable rows, or None when nothing of the ping can be used.
    problems : dict of str to int
        Rejections by reason (see :func:`screen_ping`).
    detail : str
        Why the whole ping was rejected, for a log line; empty otherwise.
    """

    echoes: EchoArrays | None
    problems: dict
    detail: str = ""


def screen_ping(echoes: EchoArrays, layout) -> Screened:
    """Keep what is usable of a ping for ``layout``; count the rest by reason.

    Every entry point (the driver's hardware and topic sources, the localiser,
    the classifier) screens pings with this one function, so they agree on what
    a usable echo row is, and on the row indices of what they keep.

    Whole-ping rejections (the ping cannot be read at all):
    ``wrong_receivers_per_group`` (the TOF columns are not the layout's K),
    ``bad_speed_of_sound`` (not finite, or outside 250..450 m/s),
    ``missing_phase_delay`` (a triad ping without K - 1 phase delays per row).
    Row and value rejections (the rest of the ping is still used): those of
    :func:`sanitize`, and ``bad_phase_delay`` (a phase delay that is not finite
    or longer than the longest TOF, replaced by NaN: that echo's bearing is
    then not computed).

    Parameters
    ----------
    echoes : EchoArrays
        A ping as received, with its speed of sound, m/s.
    layout : sonar_ring.geometry.Layout
        The sensor the ping must fit.
    """
    k = layout.receivers_per_group
    speed = echoes.speed_of_sound
    if echoes.tof.ndim != 2 or echoes.tof.shape[1] != k:
        return Screened(None, {"wrong_receivers_per_group": 1},
                        f"TOF shape {echoes.tof.shape}, layout {layout.name} has {k} receivers per group")
    if not (np.isfinite(speed) and SLOWEST_SPEED_OF_SOUND <= speed <= FASTEST_SPEED_OF_SOUND):
        return Screened(None, {"bad_speed_of_sound": 1}, f"speed of sound {speed} m/s is outside "
                        f"{SLOWEST_SPEED_OF_SOUND:g}..{FASTEST_SPEED_OF_SOUND:g} m/s")
    if layout.kind == "triad" and echoes.phase_delay.shape[1] != k - 1:
        return Screened(None, {"missing_phase_delay": 1},
                        f"a triad needs {k - 1} phase delays per row, got {echoes.phase_delay.shape[1]}")
    longest = longest_tof(layout)
    kept, problems = sanitize(echoes, layout.n_groups, layout.group_transmitters, longest)
    phase = np.array(kept.phase_delay, dtype=float)
    with np.errstate(invalid="ignore"):  # NaN (not measured) compares False and stays NaN
        bad_phase = ~(np.abs(phase) <= longest) & ~np.isnan(phase)
    if np.any(bad_phase):
        phase[bad_phase] = np.nan
        problems["bad_phase_delay"] = int(np.count_nonzero(bad_phase))
    return Screened(replace(kept, layout=layout.name, phase_delay=phase), problems)
