"""Phase-shift azimuth from three receivers with two baselines (Kreczmer 2017).

A Kreczmer triad has three receivers on a line, ``R0 -- b1 -- R1 -- b2 -- R2``,
and one emitter.  For a narrow-band echo the hardware measures two *phase
delays*: ``t01`` (``t02``) is the time from a rising zero crossing of R0's
signal to the next rising zero crossing of R1's (R2's) signal.  A delay is
therefore known only modulo the carrier period ``T = wavelength / c``, and a
baseline over ``wavelength / 2`` gives several candidate angles (Kreczmer §3).
With two different baselines ``b1`` and ``b1 + b2`` the candidates of the two
pairs coincide only at the true angle: :func:`azimuth` enumerates the integer
orders ``(n1, n2)`` of eq 4 as an array axis and keeps the pair whose two
arcsine arguments agree within ``eps`` (eq 6).

Sign convention (checked against Kreczmer's eqs 1-3): in eq 2 receiver R1's
signal ``sin(w t - k_x b1)`` lags R0's by ``b1 sin(phi) / c``, and in eq 1
``t01 > 0`` when the wavefront reaches R0 first; so ``phi > 0`` means the echo
comes from R0's side.  Layouts list a triad's receivers counter-clockwise-most
first (``R0`` is the left one, +y, for a module facing +x), so ``phi`` is
counter-clockwise positive from the triad's broadside axis, as REP 103 wants.
The broadside axis is the R0 -> R2 direction turned +90 deg.

Frames and units: metres, seconds, radians; points are in the sensor frame's
horizontal (x, y) plane.  Invalid results carry a :class:`Reason` code, never an
exception: ``ValueError`` is raised only for bad arguments (a non-positive
baseline or wavelength, ``b1 == b2``, ...).

References: B. Kreczmer, *Azimuth angle determination for the arrival direction
of an ultrasonic echo signal*, JAMRIS 11(2), 2017 (``papers/002_...``).
"""

from __future__ import annotations

import math
from enum import IntEnum
from typing import NamedTuple

import numpy as np

__all__ = [
    "Reason",
    "AzimuthResult",
    "Robustness",
    "TriadLandmark",
    "azimuth",
    "azimuth_std",
    "angle_error",
    "plane_wave_error",
    "delay_std",
    "timing_error_budget",
    "robustness",
    "phase_delays",
    "wall_image",
    "triad_landmark",
]


class Reason(IntEnum):
    """Why a result is invalid; ``OK`` (0) where it is valid."""

    OK = 0
    """A unique (n1, n2) pair, azimuth within ``max_angle``."""
    NOT_FINITE = 1
    """An input (delay, time of flight) is NaN or infinite."""
    NO_SOLUTION = 2
    """No (n1, n2) pair makes the two arcsines agree within ``eps`` (eq 6)."""
    AMBIGUOUS = 3
    """Two or more (n1, n2) pairs agree within ``eps``."""
    OUT_OF_RANGE = 4
    """The unique solution lies beyond ``max_angle``, where uniqueness is not certified."""
    BAD_RANGE = 5
    """The path length is too short for any reflector (shorter than emitter to receivers)."""


class AzimuthResult(NamedTuple):
    """What :func:`azimuth` returns; every field has the broadcast shape ``S`` of the delays.

    Attributes
    ----------
    angle : ndarray of float, shape S
        Azimuth from the triad's broadside, rad, counter-clockwise positive.
        Finite where valid; for AMBIGUOUS the best-agreeing pair's angle and for
        OUT_OF_RANGE the estimate (both for diagnostics); NaN for NOT_FINITE and
        NO_SOLUTION.
    valid : ndarray of bool, shape S
        ``reason == Reason.OK``.
    reason : ndarray of int8, shape S
        A :class:`Reason` code.
    n1, n2 : ndarray of int, shape S
        Orders of eq 4 of the chosen pair (0 where there is none).
    candidates : ndarray of int, shape S
        Number of pairs that pass eq 6 (1 where valid).
    """

    angle: np.ndarray
    valid: np.ndarray
    reason: np.ndarray
    n1: np.ndarray
    n2: np.ndarray
    candidates: np.ndarray


class Robustness(NamedTuple):
    """Result of :func:`robustness` (Kreczmer §6.2, Table 1).

    Attributes
    ----------
    delay_error : float
        Largest timing error ``dt``, s: any errors of ``t01`` and ``t02`` within
        ``[-dt, dt]`` leave the solution unique and correct for every azimuth in
        the range.  0 when even exact delays are ambiguous.
    eps : float
        The ``eps`` of eq 6 that goes with it (the smallest grid value that always
        accepts the correct pair); 0 when even exact delays are ambiguous.
    angle_error_centre : float
        Worst-case azimuth error of the fused estimate at 0 deg for ``delay_error``,
        rad (Table 1's "min delta phi").
    angle_error_edge : float
        Worst-case azimuth error at the edge of the range, rad.
    """

    delay_error: float
    eps: float
    angle_error_centre: float
    angle_error_edge: float


class TriadLandmark(NamedTuple):
    """What :func:`triad_landmark` returns for echoes of shape ``S``.

    Attributes
    ----------
    position : ndarray, shape S + (2,)
        Landmark point in the sensor frame, m (NaN where invalid).
    bearing : ndarray, shape S
        Direction of the landmark from the triad's origin (the midpoint of R0 and
        R2) in the sensor frame, rad.
    range : ndarray, shape S
        Distance from the triad's origin to the landmark, m.
    azimuth : ndarray, shape S
        Phase azimuth relative to the triad's broadside, rad (see :func:`azimuth`).
    covariance : ndarray, shape S + (2, 2)
        First-order covariance of ``position``, m^2 (NaN where invalid).
    valid : ndarray of bool, shape S
    reason : ndarray of int8, shape S
        A :class:`Reason` code.
    """

    position: np.ndarray
    bearing: np.ndarray
    range: np.ndarray
    azimuth: np.ndarray
    covariance: np.ndarray
    valid: np.ndarray
    reason: np.ndarray


# --------------------------------------------------------------------------- arguments

def _require_positive(**values) -> None:
    for name, value in values.items():
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"doa: {name} must be a finite number > 0, got {value!r}")


def _check_triad(b1, b2, wavelength, speed_of_sound) -> None:
    _require_positive(b1=b1, b2=b2, wavelength=wavelength, speed_of_sound=speed_of_sound)
    if b1 == b2:
        raise ValueError("doa: b1 == b2 leaves eq 5 without redundancy (orders (n1, n2) and (n1 + k, n2 + 2k) "
                         "give the same sines); a triad needs two different baselines")


def _check_correlation(delay_correlation) -> None:
    if not (-1.0 < delay_correlation < 1.0):
        raise ValueError(f"doa: delay_correlation must lie in (-1, 1), got {delay_correlation!r}")


def _check_max_angle(max_angle) -> None:
    if not (0.0 < max_angle <= math.pi / 2):
        raise ValueError(f"doa: max_angle must lie in (0, pi/2] rad, got {max_angle!r}")


# --------------------------------------------------------------------------- azimuth

def _fusion_coefficients(b1: float, b2: float, delay_correlation: float) -> tuple[float, float]:
    """Weights ``(a1, a2)``, ``a1 + a2 = 1``, of the sine estimate ``a1 u1 + a2 u2``.

    ``u1 = D1 / b1`` and ``u2 = D2 / (b1 + b2)`` are eq 4's arcsine arguments with
    the path differences ``D_k = c t_0k - n_k lambda``.  The weights are the
    generalised least-squares ones for ``D = (b1, b1 + b2) sin(phi) + e`` with
    ``corr(e1, e2) = delay_correlation`` and equal variances: both delays start at
    R0's zero crossing, so R0's jitter is common to both.
    """
    b12 = b1 + b2
    w1 = b1 - delay_correlation * b12
    w2 = b12 - delay_correlation * b1
    information = b1 * w1 + b12 * w2  # = b1^2 + b12^2 - 2 rho b1 b12 > 0
    return b1 * w1 / information, b12 * w2 / information


def _candidate_orders(baseline: float, wavelength: float) -> np.ndarray:
    """Every order ``n`` with ``|p - n lambda| <= baseline`` for some ``0 <= p < lambda``."""
    reach = math.floor(baseline / wavelength) + 1
    return np.arange(-reach, reach + 1)


def azimuth(t01, t02, b1, b2, wavelength, speed_of_sound, eps, max_angle, *, delay_correlation=0.5):
    """Azimuth of an echo from a triad's two phase delays (Kreczmer eqs 1-6).

    Only a delay's value modulo the carrier period ``T = wavelength / c`` matters
    (eq 3), so wrapped hardware readings and unwrapped ideal delays give the same
    result.  Every order pair ``(n1, n2)`` whose two arcsine arguments

        ``u1 = (c t01 - n1 lambda) / b1``,  ``u2 = (c t02 - n2 lambda) / (b1 + b2)``

    both lie in [-1, 1] (eq 4) is a candidate, whatever the angle; it passes when
    ``|u1 - u2| < eps`` (eq 6).  Exactly one passing pair gives the azimuth
    ``asin(a1 u1 + a2 u2)`` with generalised least-squares weights (see
    :func:`azimuth_std`); none is NO_SOLUTION, several are AMBIGUOUS, and a unique
    solution beyond ``max_angle`` is OUT_OF_RANGE.  Candidates are searched over
    the whole arcsine domain, as in the paper's robustness analysis, so an echo
    from beyond ``max_angle`` is reported as such instead of aliasing into range.

    Parameters
    ----------
    t01, t02 : array_like of float, broadcastable to shape S
        Phase delays of R1 and R2 after R0, s (any real value; used modulo ``T``).
    b1 : float
        Distance R0 -- R1, m.
    b2 : float
        Distance R1 -- R2, m (``b2 != b1``).
    wavelength : float
        Carrier wavelength, m (Kreczmer: 8.7e-3 at 40 kHz).
    speed_of_sound : float
        m/s; the period is ``wavelength / speed_of_sound``.
    eps : float
        Tolerance of eq 6 on the difference of the two sines (Table 1; > 0).
    max_angle : float
        Largest trusted ``|azimuth|``, rad, in (0, pi/2]: the range the layout's
        robustness (:func:`robustness`) was computed for.
    delay_correlation : float, optional
        Correlation of the errors of ``t01`` and ``t02``, in (-1, 1).  0.5 (the
        default) is exact when every receiver's zero crossing has the same
        independent jitter and the timer's clock phase is shared
        (:func:`phase_delays`).

    Returns
    -------
    AzimuthResult
        ``angle`` (rad), ``valid``, ``reason``, ``n1``, ``n2``, ``candidates``,
        each of shape S.

    Raises
    ------
    ValueError
        For bad arguments: non-positive baselines, wavelength, speed or ``eps``,
        ``b1 == b2``, ``max_angle`` outside (0, pi/2], ``|delay_correlation| >= 1``.
    """
    _check_triad(b1, b2, wavelength, speed_of_sound)
    _require_positive(eps=eps)
    _check_max_angle(max_angle)
    _check_correlation(delay_correlation)
    b12 = b1 + b2
    t01, t02 = np.broadcast_arrays(np.asarray(t01, dtype=float), np.asarray(t02, dtype=float))
    # A delay is under one carrier period; beyond a second it is corrupt (and overflows below): NOT_FINITE.
    finite = (np.abs(t01) <= 1.0) & (np.abs(t02) <= 1.0)
    # Path differences modulo one wavelength, in [0, lambda).
    p1 = np.mod(np.where(finite, t01, 0.0) * speed_of_sound, wavelength)
    p2 = np.mod(np.where(finite, t02, 0.0) * speed_of_sound, wavelength)
    orders1 = _candidate_orders(b1, wavelength)
    orders2 = _candidate_orders(b12, wavelength)
    u1 = (p1[..., None] - orders1 * wavelength) / b1  # S + (N1,)
    u2 = (p2[..., None] - orders2 * wavelength) / b12  # S + (N2,)
    mismatch = np.abs(u1[..., :, None] - u2[..., None, :])  # S + (N1, N2)
    in_domain = (np.abs(u1) <= 1.0)[..., :, None] & (np.abs(u2) <= 1.0)[..., None, :]
    passing = in_domain & (mismatch < eps)
    candidates = np.where(finite, passing.sum(axis=(-2, -1)), 0)

    flat = np.where(passing, mismatch, np.inf).reshape(t01.shape + (-1,))
    best = np.argmin(flat, axis=-1)
    i1, i2 = np.divmod(best, orders2.size)
    best_u1 = np.take_along_axis(u1, i1[..., None], axis=-1)[..., 0]
    best_u2 = np.take_along_axis(u2, i2[..., None], axis=-1)[..., 0]
    a1, a2 = _fusion_coefficients(b1, b2, delay_correlation)
    # Negative GLS weights can push the fused sine just past +-1 at grazing angles.
    angle = np.arcsin(np.clip(a1 * best_u1 + a2 * best_u2, -1.0, 1.0))

    reason = np.full(t01.shape, Reason.OK, dtype=np.int8)
    reason[np.abs(angle) > max_angle] = Reason.OUT_OF_RANGE
    reason[candidates > 1] = Reason.AMBIGUOUS
    reason[candidates == 0] = Reason.NO_SOLUTION
    reason[~finite] = Reason.NOT_FINITE
    has_pair = candidates > 0
    return AzimuthResult(
        angle=np.where(has_pair, angle, np.nan),
        valid=reason == Reason.OK,
        reason=reason,
        n1=np.where(has_pair, orders1[i1], 0),
        n2=np.where(has_pair, orders2[i2], 0),
        candidates=candidates,
    )


# --------------------------------------------------------------------------- error models

def azimuth_std(angle, b1, b2, speed_of_sound, delay_std, *, delay_correlation=0.5):
    """First-order standard deviation of :func:`azimuth` for the correct (n1, n2), rad.

    With delay errors of standard deviation ``sigma`` and correlation ``rho``, the
    generalised least-squares sine has variance
    ``(c sigma)^2 (1 - rho^2) / (b1^2 + b12^2 - 2 rho b1 b12)`` (``b12 = b1 + b2``),
    and ``d(phi) = d(sin phi) / cos(phi)`` (Kreczmer eq 8 for the fused estimate).

    Parameters
    ----------
    angle : array_like
        Azimuth, rad, |angle| < pi/2.
    b1, b2 : float
        Baselines, m.
    speed_of_sound : float
        m/s.
    delay_std : array_like
        Standard deviation of each phase delay, s (see :func:`delay_std`).
    delay_correlation : float, optional
        Correlation of the two delays' errors (0.5 for the hardware model).

    Returns
    -------
    ndarray
        Standard deviation of the azimuth, rad, broadcast shape of the inputs.
    """
    _check_triad(b1, b2, 1.0, speed_of_sound)
    _check_correlation(delay_correlation)
    b12 = b1 + b2
    rho = delay_correlation
    sine_std = speed_of_sound * np.asarray(delay_std, dtype=float) * math.sqrt(
        (1.0 - rho**2) / (b1**2 + b12**2 - 2.0 * rho * b1 * b12))
    return sine_std / np.cos(np.asarray(angle, dtype=float))


def angle_error(angle, baseline, speed_of_sound, delay_error):
    """Azimuth error caused by a timing error on one receiver pair, rad (Kreczmer eq 8).

    ``d(phi) = c dt / (b sqrt(1 - sin^2 phi))``; shapes broadcast.

    Parameters
    ----------
    angle : array_like
        Azimuth, rad.
    baseline : array_like
        Receiver separation ``b``, m.
    speed_of_sound : float
        m/s.
    delay_error : array_like
        Timing error ``dt``, s.
    """
    return (speed_of_sound * np.asarray(delay_error, dtype=float)
            / (np.asarray(baseline, dtype=float) * np.cos(np.asarray(angle, dtype=float))))


def plane_wave_error(distance, baseline):
    """Path error of the plane-wave assumption, m (Kreczmer eq 7).

    ``ds = sqrt(d^2 + b^2) - d`` for a source at distance ``d`` broadside of R0
    and a receiver ``b`` away, computed as ``b^2 / (sqrt(d^2 + b^2) + d)``,
    which does not cancel; ``~ b^2 / (2 d)`` for ``d >> b``.  Divide by the
    speed of sound for the delay error ``tau`` (1 mm is about 2.92 us).

    Parameters
    ----------
    distance : array_like
        Source distance ``d``, m.
    baseline : array_like
        Receiver separation ``b``, m.
    """
    d = np.asarray(distance, dtype=float)
    b = np.asarray(baseline, dtype=float)
    return b**2 / (np.hypot(d, b) + d)


def delay_std(crossing_std, timer_resolution):
    """Standard deviation of one phase delay as :func:`phase_delays` simulates it, s.

    A delay is the difference of two zero crossings, each with jitter
    ``crossing_std``, read by a timer of tick ``q`` whose clock phase is random
    (asynchronous to the echo) and shared by both delays: variance
    ``2 crossing_std^2 + q^2 / 6``.  Both terms correlate by exactly 0.5 between
    ``t01`` and ``t02`` (R0's crossing and the clock phase are shared), the
    default ``delay_correlation`` of :func:`azimuth`.

    Parameters
    ----------
    crossing_std : array_like
        Jitter of each receiver's rising zero crossing, s.
    timer_resolution : array_like
        Timer tick ``q``, s (Kreczmer: 0.33e-6).
    """
    crossing_std = np.asarray(crossing_std, dtype=float)
    timer_resolution = np.asarray(timer_resolution, dtype=float)
    return np.sqrt(2.0 * crossing_std**2 + timer_resolution**2 / 6.0)


def timing_error_budget(noise_std, timer_resolution, plane_wave_delay=0.0):
    """Worst-case timing error ``dt = dt_n + dt_r + tau`` of Kreczmer §5 and §7, s.

    The noise part is ``3 sigma`` and the timer adds its full resolution, as in
    the paper's experiment (§7); ``tau`` is the plane-wave error (eq 7 divided by
    the speed of sound).  Compare the result with :func:`robustness`'s
    ``delay_error`` to see whether a layout's solutions stay unique.

    Parameters
    ----------
    noise_std : array_like
        Standard deviation of a delay from noise, s.
    timer_resolution : array_like
        Timer tick, s.
    plane_wave_delay : array_like, optional
        ``tau``, s.
    """
    return (3.0 * np.asarray(noise_std, dtype=float) + np.asarray(timer_resolution, dtype=float)
            + np.asarray(plane_wave_delay, dtype=float))


# --------------------------------------------------------------------------- robustness

ROBUSTNESS_ANGLE_STEP = math.radians(0.05)
"""Default azimuth grid step of :func:`robustness`, rad (Table 1 comes out the same for 0.01 to 0.5 deg)."""


def robustness(b1, b2, max_angle, wavelength, speed_of_sound, *, delay_step=0.1e-6, eps_step=0.01,
               angle_step=ROBUSTNESS_ANGLE_STEP, delay_correlation=0.5, max_delay_error=20e-6):
    """Largest tolerable timing error of a triad and its ``eps`` (Kreczmer §6.2, Table 1).

    The paper's procedure: for ``dt = 0, delay_step, 2 delay_step, ...``, for every
    azimuth in ``[-max_angle, max_angle]`` and every pair of delay errors in
    ``[-dt, dt]``, the correct (n1, n2) must pass eq 6 -- else ``eps`` is raised --
    and no other pair may pass -- else the previous ``(dt, eps)`` is the answer.

    Here the errors are handled exactly instead of on a grid: an error ``dt_k``
    shifts ``u_k`` by ``c dt_k / b_k``, so the correct pair's mismatch is at most
    ``c dt (1/b1 + 1/(b1 + b2))`` and ``eps`` is the smallest multiple of
    ``eps_step`` above it; a wrong pair is the correct one shifted by
    ``(k1 lambda / b1, k2 lambda / (b1 + b2))``, and the interval its mismatch
    sweeps over the error box (clipped to the arcsine domain [-1, 1]) is tested
    against ``(-eps, eps)``.  Only the azimuth runs over a grid (``angle_step``).
    When the correct arcsine leaves [-1, 1] at the edge of the range no ``eps``
    can recover it, so that ``dt`` fails too.  (The paper's loop kept raising
    ``eps`` in that case until a wrong pair passed, and reported that inflated
    ``eps``: Table 1's 0.4 for (4, 11) mm at +-60 deg, where 1.5 us needs 0.17.)

    Parameters
    ----------
    b1, b2 : float
        Baselines R0 -- R1 and R1 -- R2, m.
    max_angle : float
        Half-width of the azimuth range, rad, in (0, pi/2].
    wavelength : float
        Carrier wavelength, m.
    speed_of_sound : float
        m/s.
    delay_step : float, optional
        Step of ``dt``, s (0.1 us reproduces Table 1's resolution).
    eps_step : float, optional
        Step of ``eps`` (0.01, Table 1's resolution).
    angle_step : float, optional
        Azimuth grid step, rad.
    delay_correlation : float, optional
        Used only for the angle errors of the fused estimate (see :func:`azimuth`).
    max_delay_error : float, optional
        Where the search stops, s.

    Returns
    -------
    Robustness
        ``delay_error`` (s), ``eps``, ``angle_error_centre`` and
        ``angle_error_edge`` (rad).
    """
    _check_triad(b1, b2, wavelength, speed_of_sound)
    _check_max_angle(max_angle)
    _check_correlation(delay_correlation)
    _require_positive(delay_step=delay_step, eps_step=eps_step, angle_step=angle_step,
                      max_delay_error=max_delay_error)
    b12 = b1 + b2
    n_angles = math.ceil(2.0 * max_angle / angle_step) + 1
    sines = np.sin(np.linspace(-max_angle, max_angle, n_angles))[:, None]  # (A, 1)
    edge_sine = math.sin(max_angle)
    # A wrong pair moves a noisy u (|u| <= 1 + half-width < 2) back into [-1, 1]: a shift below 4 = |k| lambda / b.
    k1 = np.arange(-math.ceil(4 * b1 / wavelength), math.ceil(4 * b1 / wavelength) + 1)
    k2 = np.arange(-math.ceil(4 * b12 / wavelength), math.ceil(4 * b12 / wavelength) + 1)
    shift1 = k1 * wavelength / b1  # (K1,)
    shift2 = k2 * wavelength / b12  # (K2,)
    wrong = (k1[:, None] != 0) | (k2[None, :] != 0)  # (K1, K2)

    accepted = None
    for step in range(math.floor(max_delay_error / delay_step) + 1):
        dt = step * delay_step
        half1 = speed_of_sound * dt / b1  # half-width of u1's error interval
        half2 = speed_of_sound * dt / b12
        if edge_sine + max(half1, half2) > 1.0:
            break
        eps = eps_step * (math.floor((half1 + half2) / eps_step) + 1)
        low1 = np.maximum(sines - half1 - shift1, -1.0)  # (A, K1)
        high1 = np.minimum(sines + half1 - shift1, 1.0)
        low2 = np.maximum(sines - half2 - shift2, -1.0)  # (A, K2)
        high2 = np.minimum(sines + half2 - shift2, 1.0)
        exists = (low1 <= high1)[:, :, None] & (low2 <= high2)[:, None, :]
        mismatch_low = low1[:, :, None] - high2[:, None, :]
        mismatch_high = high1[:, :, None] - low2[:, None, :]
        if np.any(exists & wrong & (mismatch_low < eps) & (mismatch_high > -eps)):
            break
        accepted = (dt, eps, half1, half2)
    if accepted is None:
        return Robustness(0.0, 0.0, 0.0, 0.0)
    dt, eps, half1, half2 = accepted
    a1, a2 = _fusion_coefficients(b1, b2, delay_correlation)
    sine_error = abs(a1) * half1 + abs(a2) * half2
    return Robustness(
        delay_error=dt,
        eps=eps,
        angle_error_centre=math.asin(min(sine_error, 1.0)),
        angle_error_edge=math.asin(min(edge_sine + sine_error, 1.0)) - max_angle,
    )


# --------------------------------------------------------------------------- forward model

def phase_delays(source_xy, receivers_xy, wavelength, speed_of_sound, *, far_field=False, crossing_std=0.0,
                 timer_resolution=0.0, rng=None):
    """Phase delays a Kreczmer module measures for an echo from a point source, s.

    Kreczmer §4: once all receivers are above threshold, a timer starts at a
    rising zero crossing of R0's signal and stops, for receiver k, at the next
    rising zero crossing of R_k's signal.  For a steady narrow-band burst this is
    the arrival-time difference ``t_k - t_0`` reduced to ``[0, T)``, ``T`` the
    carrier period.  For a wall echo pass the emitter's mirror image
    (:func:`wall_image`) as the source.

    Noise, applied where the hardware makes it: each receiver's zero crossing
    jitters by ``crossing_std`` *before* the reduction (so a crossing pushed
    ahead of R0's wraps to nearly ``T``, as on the hardware); the timer then
    counts whole ticks ``q`` of a clock whose phase is random (asynchronous to
    the echo) and shared by all receivers of the echo, which is unbiased with an
    error below ``q`` (see :func:`delay_std`).  The reading can reach ``T + q``.

    Parameters
    ----------
    source_xy : array_like, shape (..., D)
        Source position (the emitter's image for a mirror echo), m; D = 2 or 3.
    receivers_xy : array_like, shape (K, D) or (..., K, D)
        Receiver positions R0 ... R(K-1), m, in the same frame.
    wavelength, speed_of_sound : float
        Carrier wavelength (m) and speed of sound (m/s); ``T = wavelength / c``.
    far_field : bool, optional
        False: exact spherical wave (near field).  True: plane wave arriving
        from the source's direction as seen from the midpoint of R0 and R(K-1).
    crossing_std : float, optional
        Zero-crossing jitter of each receiver, s.
    timer_resolution : float, optional
        Timer tick, s (Kreczmer: 0.33e-6); 0 for exact times.
    rng : numpy.random.Generator, optional
        Random numbers for the noise (a fresh default generator when None).

    Returns
    -------
    ndarray, shape (..., K - 1)
        ``t01, t02, ...``, s (NaN where the source is not finite).
    """
    _require_positive(wavelength=wavelength, speed_of_sound=speed_of_sound)
    if not (crossing_std >= 0 and timer_resolution >= 0):
        raise ValueError(f"phase_delays: crossing_std and timer_resolution must be >= 0, "
                         f"got {crossing_std!r}, {timer_resolution!r}")
    source = np.asarray(source_xy, dtype=float)[..., None, :]  # (..., 1, D)
    receivers = np.asarray(receivers_xy, dtype=float)  # (..., K, D)
    if receivers.ndim < 2 or receivers.shape[-2] < 2:
        raise ValueError(f"phase_delays: receivers_xy needs shape (K >= 2, D), got {receivers.shape}")
    if far_field:
        origin = 0.5 * (receivers[..., :1, :] + receivers[..., -1:, :])
        towards = source - origin
        towards = towards / np.linalg.norm(towards, axis=-1, keepdims=True)
        path = -np.sum((receivers - origin) * towards, axis=-1)
    else:
        path = np.linalg.norm(source - receivers, axis=-1)
    crossing = path / speed_of_sound  # (..., K), up to a common offset
    if crossing_std > 0 or timer_resolution > 0:
        rng = np.random.default_rng() if rng is None else rng
    if crossing_std > 0:
        crossing = crossing + rng.normal(0.0, crossing_std, crossing.shape)
    period = wavelength / speed_of_sound
    delays = np.mod(crossing[..., 1:] - crossing[..., :1], period)
    if timer_resolution > 0:
        clock_phase = rng.uniform(0.0, timer_resolution, delays.shape[:-1] + (1,))
        delays = np.floor((clock_phase + delays) / timer_resolution) * timer_resolution
    return delays


def wall_image(points, wall_distance, wall_normal_angle):
    """Mirror image of points in a wall, m.

    The wall is the vertical plane ``{p : n . p = wall_distance}`` with the unit
    normal ``n = (cos a, sin a, 0)``; a wall echo reaches a receiver along the
    straight line from the emitter's image (Kreczmer Fig. 19).

    Parameters
    ----------
    points : array_like, shape (..., D)
        Points, m; D = 2 (x, y) or 3 (x, y, z; z is unchanged).
    wall_distance : array_like
        Signed distance of the wall from the frame origin along ``n``, m.
    wall_normal_angle : array_like
        Direction ``a`` of the normal, rad.

    Returns
    -------
    ndarray, shape (..., D)
    """
    points = np.asarray(points, dtype=float)
    a = np.asarray(wall_normal_angle, dtype=float)
    normal = np.zeros(a.shape + (points.shape[-1],))
    normal[..., 0] = np.cos(a)
    normal[..., 1] = np.sin(a)
    height = np.sum(points * normal, axis=-1) - np.asarray(wall_distance, dtype=float)
    return points - 2.0 * height[..., None] * normal


# --------------------------------------------------------------------------- landmark

def triad_landmark(receivers_xy, emitter_xy, tofs, t01, t02, wavelength, speed_of_sound, eps, max_angle, *,
                   delay_std, tof_std, height_offset=0.0, delay_correlation=0.5, speed_of_sound_std=0.0):
    """Landmark from one triad's echoes: bearing from phase, range from time of flight.

    The ray starts at the triad's origin ``M`` (the midpoint of R0 and R2, where
    the longer baseline's hyperbola has its asymptote) in the direction
    ``yaw + phi``, with ``yaw`` the broadside direction and ``phi`` from
    :func:`azimuth`.  The landmark is the point ``Q`` on this ray whose
    emitter-to-``Q``-to-``M`` path has the measured horizontal length
    ``d = sqrt((c tof)^2 - height_offset^2)`` (``tof`` the mean of R0's and R2's,
    the path to ``M`` to first order):
    ``|Q - E| + |Q - M| = d``, solved in closed form as
    ``r = (d^2 - |M - E|^2) / (2 (d + (M - E) . u))``.  This needs no reflector
    class: for a wall it is the specular reflection point (the ray runs towards
    the emitter's image, and ``|Q - E| = |Q - E'|`` on the wall), for an edge it
    is the edge itself, and for a corner it is the apex when the emitter sits at
    ``M`` (close to it otherwise).  Kreczmer's Figs. 27-28 plot these points.

    The azimuth is the plane-wave one; in the near field the R0 -- R1 pair sees the
    source from its own midpoint ``m1``, which biases ``phi`` by about
    ``a1 |m1 - M| cos(phi) / distance`` (``a1`` the pair's GLS weight, ``distance``
    that of the source -- for a wall, of the emitter's image): 0.01 deg for the
    shipped layout and a wall 1 m away, far below the noise.

    The covariance is first order in ``phi`` (standard deviation
    :func:`azimuth_std`) and ``d`` (the two TOFs' mean, ``c tof_std / sqrt 2``,
    plus ``tof * speed_of_sound_std``), which are independent.

    Parameters
    ----------
    receivers_xy : array_like, shape (3, 2)
        R0, R1, R2 in the sensor frame, m, collinear, R0 the counter-clockwise-most.
    emitter_xy : array_like, shape (2,)
        Emitter position, m.
    tofs : array_like, shape S + (3,)
        Times of flight at R0, R1, R2, s (R1's is not used).
    t01, t02 : array_like, shape S
        Phase delays, s (see :func:`azimuth`).
    wavelength, speed_of_sound, eps, max_angle : float
        As for :func:`azimuth`.
    delay_std : float
        Standard deviation of one phase delay, s (:func:`delay_std`).
    tof_std : float
        Standard deviation of one time of flight, s.
    height_offset : float, optional
        Emitter minus receiver height, m, for the exact vertical correction of
        vertically extruded reflectors (walls, edges, corners).
    delay_correlation : float, optional
        As for :func:`azimuth`.
    speed_of_sound_std : float, optional
        Uncertainty of the speed of sound, m/s.

    Returns
    -------
    TriadLandmark
        Position, bearing, range, azimuth, covariance, valid and reason per echo.

    Raises
    ------
    ValueError
        Receivers not of shape (3, 2), not collinear, not ordered R0 -- R1 -- R2,
        or any argument :func:`azimuth` rejects; negative standard deviations.
    """
    receivers = np.asarray(receivers_xy, dtype=float)
    emitter = np.asarray(emitter_xy, dtype=float)
    if receivers.shape != (3, 2) or emitter.shape != (2,):
        raise ValueError(f"triad_landmark: need receivers_xy (3, 2) and emitter_xy (2,), "
                         f"got {receivers.shape} and {emitter.shape}")
    if not (delay_std >= 0 and tof_std >= 0 and speed_of_sound_std >= 0):
        raise ValueError("triad_landmark: delay_std, tof_std and speed_of_sound_std must be >= 0")
    span = receivers[2] - receivers[0]
    b12 = float(np.linalg.norm(span))
    b1 = float(np.linalg.norm(receivers[1] - receivers[0]))
    b2 = float(np.linalg.norm(receivers[2] - receivers[1]))
    # R1 must lie on the segment R0 R2, within rounding, or eq 4 does not hold.
    if b12 == 0 or abs(b1 + b2 - b12) > 1e-9 * max(b12, 1e-3):
        raise ValueError(f"triad_landmark: receivers must be collinear in the order R0, R1, R2 "
                         f"(|R0R1| + |R1R2| = {b1 + b2!r} m, |R0R2| = {b12!r} m)")
    result = azimuth(t01, t02, b1, b2, wavelength, speed_of_sound, eps, max_angle,
                     delay_correlation=delay_correlation)
    angle = np.where(np.isfinite(result.angle), result.angle, 0.0)  # NaN only where already invalid
    origin = 0.5 * (receivers[0] + receivers[2])
    broadside = math.atan2(span[0], -span[1])  # R0 -> R2 turned +90 deg
    bearing = broadside + angle
    direction = np.stack([np.cos(bearing), np.sin(bearing)], axis=-1)
    direction_rate = np.stack([-np.sin(bearing), np.cos(bearing)], axis=-1)  # d(direction)/d(bearing)

    tofs = np.asarray(tofs, dtype=float)
    tof = 0.5 * (tofs[..., 0] + tofs[..., 2])
    tof_finite = np.isfinite(tof)
    tof = np.where(tof_finite, tof, 0.0)
    slant = speed_of_sound * tof
    offset = origin - emitter  # w = M - E
    offset_sq = float(offset @ offset)
    horizontal_sq = slant**2 - height_offset**2
    path = np.sqrt(np.maximum(horizontal_sq, 0.0))
    reaches = (slant > 0) & (horizontal_sq > 0) & (path > math.sqrt(offset_sq))
    along = direction @ offset  # w . u
    half_denominator = np.where(reaches, path + along, 1.0)  # > 0 wherever path > |w|
    numerator = path**2 - offset_sq
    distance = numerator / (2.0 * half_denominator)
    position = origin + distance[..., None] * direction

    # Jacobian of Q = M + r u with respect to (bearing, path).
    dr_dpath = (2.0 * path * half_denominator - numerator) / (2.0 * half_denominator**2)
    dr_dbearing = -numerator * (direction_rate @ offset) / (2.0 * half_denominator**2)
    jac_bearing = distance[..., None] * direction_rate + dr_dbearing[..., None] * direction
    jac_path = dr_dpath[..., None] * direction
    # sin(phi) is proportional to c (lambda = c / f too), so d(phi) = tan(phi) dc / c.
    bearing_var = (azimuth_std(angle, b1, b2, speed_of_sound, delay_std, delay_correlation=delay_correlation) ** 2
                   + (np.tan(angle) * speed_of_sound_std / speed_of_sound) ** 2)
    # Mean of two independent TOFs; d = sqrt(s^2 - dz^2), so dd/ds = s / d.
    slant_var = (speed_of_sound * tof_std) ** 2 / 2.0 + (tof * speed_of_sound_std) ** 2
    path_var = slant_var * (slant / np.where(reaches, path, 1.0)) ** 2
    covariance = (bearing_var[..., None, None] * jac_bearing[..., :, None] * jac_bearing[..., None, :]
                  + path_var[..., None, None] * jac_path[..., :, None] * jac_path[..., None, :])

    reason = result.reason.copy()
    reason[(reason == Reason.OK) & ~reaches] = Reason.BAD_RANGE
    reason[~tof_finite] = Reason.NOT_FINITE
    valid = reason == Reason.OK
    return TriadLandmark(
        position=np.where(valid[..., None], position, np.nan),
        bearing=np.where(valid, bearing, np.nan),
        range=np.where(valid, distance, np.nan),
        azimuth=result.angle,
        covariance=np.where(valid[..., None, None], covariance, np.nan),
        valid=valid,
        reason=reason,
    )
