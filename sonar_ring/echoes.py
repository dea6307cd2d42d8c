"""One ping's echoes as arrays: what a driver source produces and the localiser reads.

Mirrors the ``sonar_ring/Echoes`` message (N echo rows, K receivers per group);
``sonar_ring.ros.convert`` turns one into the other without a per-element loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sonar_ring.compiled import kernel

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


def load_kernels() -> None:
    """Load the compiled row checks of :func:`screen_ping` now instead of at the first ping.

    Every node that screens pings calls it at start: the first call of any kernel
    also starts numba, which a ping should not wait for.
    """
    _screen_rows(np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64), np.ones((1, 2)), np.zeros((1, 1)), 1,
                 np.zeros((1, 1), dtype=np.int64), 1.0)


SCREEN_PROBLEMS = ("unknown_group", "unknown_transmitter", "not_finite_tof", "not_positive_tof", "tof_too_long",
                   "empty_row", "bad_phase_delay")
"""What :func:`screen_ping` counts by row or by value, in the order of :func:`_screen_rows`' counts."""
ROW_DROPS = ("unknown_group", "unknown_transmitter", "empty_row")
"""The problems of :data:`SCREEN_PROBLEMS` that drop a row."""


@kernel
def _screen_rows(group, transmitter, tof, phase_delay, n_groups, group_transmitters, max_tof):
    """The row and value checks of :func:`screen_ping`: which rows to keep, and the problems' counts.

    ``group`` and ``transmitter`` (N,) int; ``tof`` (N, K) s, in which TOFs that
    are infinite, not positive or longer than ``max_tof`` are set to NaN here;
    ``phase_delay`` (N, P) s, in which a kept row's values that are infinite or
    longer than ``max_tof`` are set to NaN here; ``group_transmitters`` (G, M).
    Returns ``keep`` (N,) bool and the counts of :data:`SCREEN_PROBLEMS` (7,),
    TOF values counted only in rows of a known group and transmitter, phase
    delays only in kept rows.
    """
    n_echoes, n_receivers = tof.shape
    keep = np.zeros(n_echoes, dtype=np.bool_)
    counts = np.zeros(len(SCREEN_PROBLEMS), dtype=np.int64)
    for n in range(n_echoes):
        if not 0 <= group[n] < n_groups:
            counts[0] += 1
            continue
        allowed = False
        for slot in range(group_transmitters.shape[1]):
            allowed = allowed or group_transmitters[group[n], slot] == transmitter[n]
        heard = False
        for k in range(n_receivers):
            value = tof[n, k]
            if np.isinf(value):
                counts[2] += allowed
                tof[n, k] = np.nan
            elif value <= 0:
                counts[3] += allowed
                tof[n, k] = np.nan
            elif value > max_tof:
                counts[4] += allowed
                tof[n, k] = np.nan
            elif value == value:
                heard = True
        if not allowed:
            counts[1] += 1
        elif not heard:
            counts[5] += 1
        else:
            keep[n] = True
            for column in range(phase_delay.shape[1]):
                value = phase_delay[n, column]
                if value == value and not abs(value) <= max_tof:  # NaN: not measured, kept as it is
                    counts[6] += 1
                    phase_delay[n, column] = np.nan
    return keep, counts


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
        The usable rows, or None when nothing of the ping can be used.  TOFs
        and phase delays are new arrays; the other fields are the ping's own
        arrays when no row was dropped.
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

    Every entry point (the driver's sources, the localiser) screens pings with
    this one function, through :func:`sonar_ring.ping_stage.check_ping`, so they
    agree on what a usable echo row is.

    Whole-ping rejections (the ping cannot be read at all):
    ``mismatched_rows`` (its arrays do not have one row per echo, or the
    amplitudes and phase delays are not 2-D),
    ``wrong_receivers_per_group`` (the TOF columns are not the layout's K),
    ``bad_speed_of_sound`` (not finite, or outside 250..450 m/s),
    ``missing_phase_delay`` (a triad ping without K - 1 phase delays per row).
    Row and value rejections (the rest of the ping is still used), counted by
    reason: rows of an ``unknown_group`` or ``unknown_transmitter`` (not one of
    its group's) are dropped; TOFs that are ``not_finite_tof``,
    ``not_positive_tof`` or ``tof_too_long`` (over :func:`longest_tof`) become
    NaN, a missed echo, and a row left without any TOF is dropped
    (``empty_row``); a ``bad_phase_delay`` (not finite, or longer than the
    longest TOF) becomes NaN: that echo's bearing is then not computed.

    Parameters
    ----------
    echoes : EchoArrays
        A ping as received, with its speed of sound, m/s.
    layout : sonar_ring.geometry.Layout
        The sensor the ping must fit.
    """
    k = layout.receivers_per_group
    speed = echoes.speed_of_sound
    rows = len(echoes.tof)
    # Checked before the row kernel: compiled indexing does not check bounds.
    if (echoes.amplitude.ndim != 2 or echoes.phase_delay.ndim != 2
            or any(len(array) != rows for array in (echoes.group, echoes.transmitter, echoes.amplitude,
                                                    echoes.phase_delay))):
        return Screened(None, {"mismatched_rows": 1},
                        f"rows: {len(echoes.group)} groups, {len(echoes.transmitter)} transmitters, {rows} TOF, "
                        f"amplitude {echoes.amplitude.shape}, phase delay {echoes.phase_delay.shape}")
    if echoes.tof.ndim != 2 or echoes.tof.shape[1] != k:
        return Screened(None, {"wrong_receivers_per_group": 1},
                        f"TOF shape {echoes.tof.shape}, layout {layout.name} has {k} receivers per group")
    if not (math.isfinite(speed) and SLOWEST_SPEED_OF_SOUND <= speed <= FASTEST_SPEED_OF_SOUND):
        return Screened(None, {"bad_speed_of_sound": 1}, f"speed of sound {speed} m/s is outside "
                        f"{SLOWEST_SPEED_OF_SOUND:g}..{FASTEST_SPEED_OF_SOUND:g} m/s")
    if layout.kind == "triad" and echoes.phase_delay.shape[1] != k - 1:
        return Screened(None, {"missing_phase_delay": 1},
                        f"a triad needs {k - 1} phase delays per row, got {echoes.phase_delay.shape[1]}")
    # Copies: the row checks set bad values to NaN in place, and the caller's ping stays as it came; as
    # C-contiguous float64 and int64 (a message's uint16 groups, uint8 transmitters) they are the types the
    # kernel is compiled for.
    tof, phase_delay = (np.array(array, dtype=float, order="C") for array in (echoes.tof, echoes.phase_delay))
    keep, counts = _screen_rows(np.asarray(echoes.group).astype(np.int64),
                                np.asarray(echoes.transmitter).astype(np.int64), tof, phase_delay, layout.n_groups,
                                np.ascontiguousarray(layout.group_transmitters, dtype=np.int64), longest_tof(layout))
    problems = {reason: n for reason, n in zip(SCREEN_PROBLEMS, counts.tolist(), strict=True) if n}
    rows = (echoes.group, echoes.transmitter, tof, echoes.amplitude, phase_delay)
    if any(reason in problems for reason in ROW_DROPS):  # else every row is kept, as in most pings: no gather
        rows = tuple(array[keep] for array in rows)
    return Screened(EchoArrays(layout.name, speed, *rows), problems)
