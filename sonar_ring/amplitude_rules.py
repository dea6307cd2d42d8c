"""Barshan & Kuc (1990) for transducer pairs: planes and corners told apart by their amplitudes.

A pair of transducers ``a`` and ``b`` that both transmit and receive hears four
amplitudes of one reflector, ``A_aa', A_ab', A_ba', A_bb'``; eqs 13-14 decide
PLANE or CORNER when the relevant differences exceed ``6 sigma``, otherwise
UNKNOWN, with a margin and a confidence (:mod:`sonar_ring.confidence`).  Beside
the rule, the paper's companions to it for such pairs: the inclination of the
plane or corner (eqs 21-23) and its variance, the separation limits and working
range of a pair (eqs 26-29), the pair chosen on a linear array (eq 30), and
the fusion of several pairs' estimates (eq 41).

A single emitter (Browne's ring) has no amplitude evidence: see
:mod:`sonar_ring.ring_consistency`.

Frames and units (REP 103): metres, radians, the sensor frame with x forward, y left,
angles counter-clockwise.  A Barshan & Kuc pair has transducer ``a`` on the left
(+y) and ``b`` on the right, both facing +x; a positive inclination turns the plane's
normal (or the direction to the corner) towards ``a``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sonar_ring.checks import positive_finite
from sonar_ring.confidence import confidence_from_margin
from sonar_ring.landmarks import CORNER, PLANE, UNKNOWN

DECISION_MARGIN = 6.0
"""Barshan & Kuc eqs 13-14: one amplitude is *greater* than another only by more than 6 sigma."""

MARGIN_RULES = ("paper", "amplitude_model")
"""Ways to turn the 6-sigma margin into separation limits (see :func:`separation_limits`)."""


@dataclass(frozen=True)
class Classification:
    """Class decisions for a batch of echoes.

    Attributes
    ----------
    cls : ndarray of uint8, shape (N,)
        Class code per echo: :data:`UNKNOWN`, :data:`PLANE`, :data:`CORNER` or :data:`EDGE`.
    margin : ndarray of float, shape (N,)
        By how many standard deviations of the tested difference the deciding test
        passed its threshold, >= 0; 0 where ``cls`` is UNKNOWN.
    confidence : ndarray of float, shape (N,)
        ``2 Phi(margin) - 1``, in [0, 1]; 0 where ``cls`` is UNKNOWN.
    """

    cls: np.ndarray
    margin: np.ndarray
    confidence: np.ndarray


def _beam_and_noise(theta0, sigma_rel, margin_rule):
    """Validate the beam half-angle, relative noise and margin rule; return ``sqrt(-ln(1 - 6 sigma))``."""
    if not (np.ndim(theta0) == 0 and np.isfinite(theta0) and 0 < theta0 < np.pi / 2):
        raise ValueError(f"theta0 must be a beam half-angle in (0, pi/2) rad, got {theta0!r}")
    if not (np.ndim(sigma_rel) == 0 and np.isfinite(sigma_rel) and 0 < sigma_rel < 1 / DECISION_MARGIN):
        raise ValueError(f"sigma_rel = sigma / A_max must be in (0, 1/6) so that a 6-sigma margin "
                         f"fits below A_max, got {sigma_rel!r}")
    if margin_rule not in MARGIN_RULES:
        raise ValueError(f"margin_rule must be one of {MARGIN_RULES}, got {margin_rule!r}")
    return np.sqrt(-np.log1p(-DECISION_MARGIN * sigma_rel))


# --------------------------------------------------------------------------- amplitude rules

def _amplitude_test(a_aa, a_ab, a_ba, a_bb, sigma):
    """Eqs 13-14 on broadcast arrays; returns (codes uint8, margin in standard deviations)."""
    sigma = positive_finite("sigma", sigma)
    a_aa, a_ab, a_ba, a_bb, sigma = np.broadcast_arrays(
        *(np.asarray(a, dtype=float) for a in (a_aa, a_ab, a_ba, a_bb)), sigma)
    threshold = DECISION_MARGIN * sigma
    # A_ab' and A_ba' travel the same path in opposite directions, so they have the same
    # mean (reciprocity); averaging halves their noise variance.  Cross amplitudes that
    # disagree by more than the decision margin cannot come from one specular reflector.
    cross = 0.5 * (a_ab + a_ba)
    reciprocal = np.abs(a_ab - a_ba) <= threshold
    direct = np.minimum(a_aa, a_bb)
    # eq 13 (PLANE): both direct amplitudes exceed the cross amplitude by 6 sigma;
    # eq 14 (CORNER): the cross amplitude exceeds either direct amplitude by 6 sigma.
    plane_margin = direct - cross - threshold
    corner_margin = cross - direct - threshold
    usable = np.isfinite(a_aa) & np.isfinite(a_ab) & np.isfinite(a_ba) & np.isfinite(a_bb) & reciprocal
    is_plane = usable & (plane_margin > 0)
    is_corner = usable & (corner_margin > 0)
    codes = np.full(a_aa.shape, UNKNOWN, dtype=np.uint8)
    codes[is_plane] = PLANE
    codes[is_corner] = CORNER
    # The tested difference is one direct amplitude minus the mean of two cross ones.
    difference_sigma = sigma * np.sqrt(1.5)
    margin = np.zeros(a_aa.shape)
    margin[is_plane] = plane_margin[is_plane] / difference_sigma[is_plane]
    margin[is_corner] = corner_margin[is_corner] / difference_sigma[is_corner]
    return codes, margin


def amplitude_rule(a_aa, a_ab, a_ba, a_bb, sigma):
    """Plane / corner decision from the four amplitudes of a transducer pair (eqs 13-14).

    ``A_xy'`` is the amplitude received by transducer ``y`` when ``x`` transmits.
    PLANE where ``min(A_aa', A_bb') - A_cross > 6 sigma``; CORNER where
    ``A_cross - min(A_aa', A_bb') > 6 sigma`` (eq 14's OR); otherwise UNKNOWN.
    ``A_cross`` is the mean of ``A_ab'`` and ``A_ba'``, equal in expectation by
    reciprocity; where they differ by more than ``6 sigma`` the echo is UNKNOWN.
    Non-finite amplitudes (missing echoes) give UNKNOWN.

    Parameters
    ----------
    a_aa, a_ab, a_ba, a_bb : array_like, broadcastable to a common shape (...)
        Amplitudes, any linear unit (typically normalised so that ``A_max = 1``).
    sigma : array_like
        Standard deviation of the additive amplitude noise (eq 12), same unit, > 0;
        broadcastable to the amplitudes.

    Returns
    -------
    ndarray of uint8, shape (...)
        :data:`UNKNOWN`, :data:`PLANE` or :data:`CORNER` per echo.

    Raises
    ------
    ValueError
        If ``sigma`` is not finite and positive.
    """
    return _amplitude_test(a_aa, a_ab, a_ba, a_bb, sigma)[0]


def classify_amplitudes(amplitude, sigma) -> Classification:
    """Amplitude rule with its confidence for a batch of pair echoes.

    Parameters
    ----------
    amplitude : array_like, shape (N, 2, 2)
        ``amplitude[n, i, j]``: received by transducer ``j`` when transducer ``i``
        transmitted, with index 0 = ``a`` (left, +y) and 1 = ``b``; so
        ``[[A_aa', A_ab'], [A_ba', A_bb']]``.
    sigma : array_like
        Amplitude noise standard deviation, > 0, scalar or shape (N,).

    Returns
    -------
    Classification
        ``cls`` in {UNKNOWN, PLANE, CORNER}; ``margin`` = by how much the deciding
        difference exceeds the 6-sigma threshold, in its standard deviation
        ``sigma * sqrt(3/2)``; ``confidence`` from it.
    """
    amplitude = np.asarray(amplitude, dtype=float)
    if amplitude.ndim != 3 or amplitude.shape[1:] != (2, 2):
        raise ValueError(f"amplitude must have shape (N, 2, 2), got {amplitude.shape}")
    codes, margin = _amplitude_test(amplitude[:, 0, 0], amplitude[:, 0, 1], amplitude[:, 1, 0],
                                    amplitude[:, 1, 1], sigma)
    return Classification(cls=codes, margin=margin, confidence=confidence_from_margin(margin))


# --------------------------------------------------------------------------- inclination

def plane_inclination(range_aa, range_bb, separation):
    """Inclination of a plane from the two direct ranges (eq 21), rad.

    ``theta_p = asin((R_bb' - R_aa') / d)``, exact for a plane: the one-way ranges
    are the perpendicular distances of ``a`` and ``b`` from it.

    Parameters
    ----------
    range_aa, range_bb : array_like, broadcastable
        One-way ranges ``R = c * tof / 2`` of the echoes ``a -> a`` and ``b -> b``, m.
    separation : array_like
        Centre-to-centre distance ``d`` of ``a`` and ``b``, m, > 0.

    Returns
    -------
    ndarray
        Angle from the pair's facing (+x) to the plane's normal, counter-clockwise
        positive (towards ``a``), rad; NaN where ``|R_bb' - R_aa'| > d`` or inputs are
        not finite.
    """
    separation = positive_finite("separation", separation)
    ratio = (np.asarray(range_bb, dtype=float) - np.asarray(range_aa, dtype=float)) / separation
    return _safe_arcsin(ratio)


def corner_inclination(range_aa, range_ab, range_bb, separation):
    """Inclination of a corner with the correction term ``s`` (eqs 22-23), rad.

    ``s = sqrt(R_ab'^2 + d^2/4) - R_ab'`` (eq 23) makes ``theta_c = 0`` at zero
    inclination.  Eq 22 as printed is corrected in two places, both checked against
    the exact ranges of eqs 18-20 in the tests: the sine carries a factor 2
    (``R_bb' - R_ab' - s ~= (d/2) sin theta``; without it eq 22 returns about half
    the angle), and the second branch, which uses ``R_aa'`` for corners on the ``b``
    side, has a minus sign.  The branch is chosen by the sign of ``R_bb' - R_aa'``,
    which also covers noisy echoes near zero inclination that satisfy neither of the
    paper's two conditions.

    Parameters
    ----------
    range_aa, range_ab, range_bb : array_like, broadcastable
        One-way ranges ``R = c * tof / 2`` of the echoes ``a -> a``, ``a -> b`` (or the
        mean of ``a -> b`` and ``b -> a``) and ``b -> b``, m.
    separation : array_like
        Centre-to-centre distance ``d`` of ``a`` and ``b``, m, > 0.

    Returns
    -------
    ndarray
        Bearing of the corner's apex from the pair centre, counter-clockwise positive,
        rad; NaN where the ratio leaves [-1, 1] or inputs are not finite.
    """
    separation = positive_finite("separation", separation)
    range_aa, range_ab, range_bb = (np.asarray(r, dtype=float) for r in (range_aa, range_ab, range_bb))
    correction = np.sqrt(np.square(range_ab) + np.square(separation) / 4) - range_ab
    towards_a = range_bb >= range_aa
    ratio = np.where(towards_a, range_bb - correction - range_ab, -(range_aa - correction - range_ab))
    return _safe_arcsin(2.0 * ratio / separation)


def inclination_variance(separation, range_sigma, inclination, cls):
    """First-order variance of :func:`plane_inclination` / :func:`corner_inclination`, rad^2.

    With independent one-way range errors of standard deviation ``sigma_R``:
    plane ``2 sigma_R^2 / (d cos theta)^2``; corner (one direct and one cross range,
    factor 2 of eq 22) ``8 sigma_R^2 / (d cos theta)^2``.  These are the ``sigma_i^2``
    of the fusion weights (eq 41).

    Parameters
    ----------
    separation : array_like
        Pair separation ``d``, m, > 0.
    range_sigma : array_like
        Standard deviation of one one-way range, m (``c * sigma_tof / 2``).
    inclination : array_like
        Inclination at which to evaluate, rad.
    cls : array_like of int
        :data:`PLANE` or :data:`CORNER`; other codes give NaN.

    Returns
    -------
    ndarray
        Variance, rad^2, broadcast shape of the arguments.
    """
    separation = positive_finite("separation", separation)
    cls = np.asarray(cls)
    factor = np.where(cls == PLANE, 2.0, np.where(cls == CORNER, 8.0, np.nan))
    return factor * np.square(range_sigma) / np.square(separation * np.cos(inclination))


def _safe_arcsin(ratio):
    ratio = np.asarray(ratio, dtype=float)
    inside = np.abs(ratio) <= 1.0  # False for NaN too
    return np.where(inside, np.arcsin(np.where(inside, ratio, 0.0)), np.nan)


# --------------------------------------------------------------------------- separation and working range

def separation_limits(range_m, theta0, sigma_rel, margin_rule="paper"):
    """Smallest and largest useful pair separation at a range (eqs 26-27).

    ``d_max = 2 R tan(theta0)`` (eq 27): beyond it the virtual receiver leaves the
    other transducer's beam.  ``d_min`` is where the plane's direct and cross
    amplitudes at normal incidence differ by 6 sigma (eqs 24-25).  Two versions:

    * ``"paper"``: eq 26 as printed, ``d_min = R tan(theta0) / 2 * sqrt(-ln(1 - 6 sigma/A_max))``;
    * ``"amplitude_model"``: the same condition solved exactly with eqs 6-8,
      ``d_min = 2 R tan(theta0 / 2 * sqrt(-ln(1 - 6 sigma/A_max)))``, about twice the
      printed value (eq 26 corresponds to ``theta_s = atan(d/R)`` instead of eq 8's
      ``atan(d/2R)``).

    Parameters
    ----------
    range_m : array_like
        Range ``R`` of the reflector from the pair centre, m; non-finite or <= 0 gives NaN.
    theta0 : float
        Beam half-angle (eq 2), rad, in (0, pi/2).
    sigma_rel : float
        Amplitude noise as a fraction of ``A_max``, in (0, 1/6).
    margin_rule : str
        ``"paper"`` (default) or ``"amplitude_model"``.

    Returns
    -------
    d_min, d_max : ndarray
        Separation limits, m, shape of ``range_m``.
    """
    root = _beam_and_noise(theta0, sigma_rel, margin_rule)
    range_m = np.asarray(range_m, dtype=float)
    range_m = np.where(np.isfinite(range_m) & (range_m > 0), range_m, np.nan)
    if margin_rule == "paper":
        d_min = range_m * np.tan(theta0) / 2 * root
    else:
        d_min = 2 * range_m * np.tan(theta0 / 2 * root)
    return d_min, 2 * range_m * np.tan(theta0)


def working_range(separation, theta0, sigma_rel, margin_rule="paper"):
    """Ranges over which a pair of separation ``d`` tells planes from corners (eqs 28-29).

    ``R_min = d / (2 tan theta0)`` (eq 28) and, with ``margin_rule="paper"``,
    ``R_max = 2 d / (tan(theta0) sqrt(-ln(1 - 6 sigma/A_max)))`` (eq 29): eqs 26-27
    solved for ``R``.  ``"amplitude_model"`` inverts the exact ``d_min`` instead (see
    :func:`separation_limits`), giving about half the printed ``R_max``.  For
    ``d = 80 mm``, ``theta0 = 10 deg``, ``sigma = 2 %``: 227 mm to 2538 mm (paper),
    1282 mm (amplitude model).

    Parameters
    ----------
    separation : array_like
        Pair separation ``d``, m; non-finite or <= 0 gives NaN.
    theta0, sigma_rel, margin_rule
        As for :func:`separation_limits`.

    Returns
    -------
    r_min, r_max : ndarray
        Working range limits, m, shape of ``separation``.
    """
    root = _beam_and_noise(theta0, sigma_rel, margin_rule)
    separation = np.asarray(separation, dtype=float)
    separation = np.where(np.isfinite(separation) & (separation > 0), separation, np.nan)
    r_min = separation / (2 * np.tan(theta0))
    if margin_rule == "paper":
        r_max = 2 * separation / (np.tan(theta0) * root)
    else:
        r_max = separation / (2 * np.tan(theta0 / 2 * root))
    return r_min, r_max


def choose_pair(separations, range_m, theta0, sigma_rel, margin_rule="paper"):
    """Index of the array pair to use at a range (eq 30).

    The pair whose separation is nearest ``(d_min + d_max) / 2`` at that range.

    Parameters
    ----------
    separations : array_like, shape (P,)
        Separations of the candidate pairs, m (e.g. ``Layout.group_separation()``).
    range_m : array_like, shape (...)
        Reflector ranges, m.
    theta0, sigma_rel, margin_rule
        As for :func:`separation_limits`.

    Returns
    -------
    ndarray of int, shape (...)
        Pair index per range; -1 where the range is not finite and positive.
    """
    separations = positive_finite("separations", separations).reshape(-1)
    d_min, d_max = separation_limits(range_m, theta0, sigma_rel, margin_rule)
    target = 0.5 * (d_min + d_max)
    distance = np.abs(separations - target[..., None])
    best = np.argmin(np.where(np.isfinite(distance), distance, np.inf), axis=-1)
    return np.where(np.isfinite(target), best, -1)


# --------------------------------------------------------------------------- fusion

def fusion_weights(variances):
    """Optimal weights of a linear fusion of independent estimates (eq 41), over the last axis.

    ``w_i = (1 / sigma_i^2) / sum_k (1 / sigma_k^2)``, which minimise the mean squared
    error of ``sum_i w_i theta_i`` under ``sum_i w_i = 1`` (eqs 31-40).  A variance
    that is not finite and > 0 (NaN, infinite, zero, negative) marks a missing
    estimate: weight 0.  A row without any usable variance gets weights all 0
    (and :func:`fuse` NaN), never NaN weights.

    Parameters
    ----------
    variances : array_like, shape (..., P)
        Error variances of the P estimates (last axis).

    Returns
    -------
    ndarray, shape (..., P)
        Weights summing to 1 along the last axis; all 0 in rows with no usable variance.
    """
    information = _information(np.asarray(variances, dtype=float))
    total = information.sum(axis=-1, keepdims=True)
    return np.divide(information, total, out=np.zeros_like(information), where=total > 0)


def fuse(estimates, variances):
    """Fuse independent estimates with the weights of eq 41 (:func:`fusion_weights`).

    An estimate that is not finite counts as missing, as does one whose variance
    is not finite and > 0.

    Parameters
    ----------
    estimates : array_like, shape (..., P)
        Estimates from P pairs (last axis); NaN where a pair has none.
    variances : array_like, shape (..., P)
        Their error variances.

    Returns
    -------
    estimate, variance : ndarray, shape (...)
        ``sum_i w_i theta_i`` and its variance ``1 / sum_i (1 / sigma_i^2)`` (the
        minimum of eq 36), over the estimates that are not missing; NaN where all are.
    """
    estimates, variances = np.broadcast_arrays(np.asarray(estimates, dtype=float),
                                               np.asarray(variances, dtype=float))
    variances = np.where(np.isfinite(estimates), variances, np.nan)  # a missing estimate: a missing variance
    weights = fusion_weights(variances)
    found = weights.sum(axis=-1) > 0
    fused = np.where(found, np.sum(weights * np.where(weights > 0, estimates, 0.0), axis=-1), np.nan)
    information = _information(variances).sum(axis=-1)
    variance = np.where(found, 1.0 / np.where(found, information, 1.0), np.nan)
    return fused, variance


def _information(variances: np.ndarray) -> np.ndarray:
    """``1 / variance`` where the variance is finite and > 0, else 0 (a missing estimate)."""
    usable = np.isfinite(variances) & (variances > 0)
    return np.where(usable, 1.0 / np.where(usable, variances, 1.0), 0.0)
