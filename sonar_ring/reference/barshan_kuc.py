"""Barshan & Kuc (1990), *Differentiating sonar reflections from corners and planes* -- formulas as printed.

Geometry (their Fig. 7).  Transducers ``a`` and ``b`` a distance ``d`` apart
both transmit and receive; ``a`` is the counter-clockwise one (at y = +d/2 in
a frame with x along the line of sight), so the inclination ``theta`` is
counter-clockwise positive as in the paper ("measuring angles in the
counterclockwise directions").  ``R`` is the range from the centre of the pair
to the reflector: for a plane the perpendicular distance, for a corner the
distance to its apex.  Ranges ``R_xy`` are *one-way*: half the path
transmitter x -> reflector -> receiver y (their eq 1, ``R0 = c t0 / 2``).

Notes from checking these against exact geometry (``test/test_reference.py``):

* eqs 15, 16, 18, 19, 20 and 21 are exact;
* eq 17 (plane, cross path) is not: the exact half path is
  ``sqrt(R^2 + d^2 cos^2(theta) / 4)``, while the printed
  ``sqrt(R^2 + d^2/4 - R d sin(theta))`` is the corner's eq 18 again; they
  agree only at theta = 0;
* eq 22 (corner inclination) as printed gives about ``asin(sin(theta) / 2)``
  on its first branch (half the inclination), and a positive angle on its
  second branch, which applies to negative inclinations.

No input checking: invalid data give NaN, as the formulas do.
"""

from __future__ import annotations

import numpy as np


def plane_ranges(R, theta, d):
    """Eqs 15-17: one-way ranges ``(R_aa', R_bb', R_ab' = R_ba')`` of a plane, m."""
    R, theta = np.asarray(R, dtype=float), np.asarray(theta, dtype=float)
    r_aa = R - d / 2 * np.sin(theta)  # (15)
    r_bb = R + d / 2 * np.sin(theta)  # (16)
    r_ab = np.sqrt(R**2 + d**2 / 4 - R * d * np.sin(theta))  # (17)
    return r_aa, r_bb, r_ab


def corner_ranges(R, theta, d):
    """Eqs 18-20: one-way ranges ``(R_aa', R_bb', R_ab' = R_ba')`` of a corner, m."""
    R, theta = np.asarray(R, dtype=float), np.asarray(theta, dtype=float)
    r_aa = np.sqrt(R**2 + d**2 / 4 - R * d * np.sin(theta))  # (18)
    r_bb = np.sqrt(R**2 + d**2 / 4 + R * d * np.sin(theta))  # (19)
    r_ab = R  # (20)
    return r_aa, r_bb, r_ab


def plane_inclination(r_aa, r_bb, d):
    """Eq 21: ``theta_p = asin((R_bb' - R_aa') / d)``, rad."""
    return np.arcsin((np.asarray(r_bb, dtype=float) - np.asarray(r_aa, dtype=float)) / d)


def corner_correction(r_ab, d):
    """Eq 23: the correction ``s = sqrt(R_ab'^2 + d^2/4) - R_ab'`` that makes theta_c(0) = 0, m."""
    r_ab = np.asarray(r_ab, dtype=float)
    return np.sqrt(r_ab**2 + d**2 / 4) - r_ab


def corner_inclination(r_aa, r_bb, r_ab, d):
    """Eq 22: corner inclination theta_c, rad; NaN where neither branch applies.

    ``asin(((R_bb' - s) - R_ab') / d)`` if ``R_bb' - s >= R_ab'``, else
    ``asin(((R_aa' - s) - R_ab') / d)`` if ``R_aa' - s >= R_ab'``.
    """
    r_aa, r_bb = np.asarray(r_aa, dtype=float), np.asarray(r_bb, dtype=float)
    s = corner_correction(r_ab, d)
    first = np.arcsin(((r_bb - s) - r_ab) / d)
    second = np.arcsin(((r_aa - s) - r_ab) / d)
    return np.where(r_bb - s >= r_ab, first, np.where(r_aa - s >= r_ab, second, np.nan))


def optimal_weights(variances):
    """Eq 41: ``w_i = (1 / sigma_i^2) / sum_k (1 / sigma_k^2)`` over the last axis."""
    inverse = 1 / np.asarray(variances, dtype=float)
    return inverse / inverse.sum(axis=-1, keepdims=True)
