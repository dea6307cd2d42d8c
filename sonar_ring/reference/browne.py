"""Browne (2011), *Bearing calculation of a single emitter sonar ring* -- the formulas as printed.

Frame.  All positions returned here are in one *pair frame*: origin at the
emitter (the ring centre ``T``), x along the pair's axis (outwards), y towards
receiver R1, so R1 = (R, +D/2) and R2 = (R, -D/2) with ``R`` the ring radius.
This is the sensor frame of a pair facing +x with R1 counter-clockwise, as in
:mod:`sonar_ring.geometry`, and it makes Browne's angles (eqs 4, 10, 17-19)
counter-clockwise positive.  Browne's Fig. 8 (the edge) instead puts the origin
between the receivers with R1 at y = -E, R2 at y = +E (E = D/2) and T at
(-R, 0); :func:`edge_solutions` returns that frame verbatim and
:func:`edge_point` maps it, ``(x + R, -y)``.

Angles are in radians (the report's 180 degrees in eq 10 is pi).  Inputs are
path lengths (eq 1 as printed, ``tof / c``, has the ratio upside down; use
``c * tof``).  No input checking: invalid data give NaN, as the formulas do.

Appendix A transcription.  The report prints the Matlab ``solve`` output six
times over (x1, x2, y1, y2, h1, h2), each copy repeating the same three
sub-expressions, with OCR/typesetting typos that differ between copies.  Every
term of the discriminant must have degree 10 in (d1, d2, E, R), of the
numerator 5 and of the denominator 4, which identifies the typos:

* discriminant term ``2*d_2^4*E^2*d_1^4`` -- the x1 copy prints ``d_2^2``
  (degree 8); the x2 and y1 copies print ``d_2^4``;
* ``E^4*d_2^6 + E^4*d_1^6`` and ``6*E^4*d_2^4*R^2`` -- the y2, h1 and h2 copies
  print ``E^4*d_1^6 + E^4*d_1^6`` and ``6*E^4*d_2^2*R^2`` (degree 8);
* y1 has a stray ``)`` after its first denominator (the y2 copy does not);
* h2 carries ``+ 4*(...)^(1/2)`` (so it would equal h1) and a trailing ``/E``
  (degree 0); it must pair with x2 (``- 4*(...)``), and the repeated last line
  of the report has no ``/E``;
* ``(...)(1/2)`` is ``(...)^(1/2)`` throughout.

The expressions below are the x2/y1 copies with these fixes, evaluated exactly
as printed (same operations in the same order).  ``h`` is the
transmitter-to-edge distance k of eq 24.
"""

from __future__ import annotations

import numpy as np


def bearing_eq4(d1, d2, separation):
    """Eq 4: ``phi_1 = asin((d2^2 - d1^2 - D^2) / (2 d1 D))``, rad, angle at R1."""
    d1, d2 = np.asarray(d1, dtype=float), np.asarray(d2, dtype=float)
    return np.arcsin((d2**2 - d1**2 - separation**2) / (2 * d1 * separation))


def bearing_eq8(d1, d2, separation):
    """Eq 8: far-field approximation ``phi_1 ~ asin((d2 - d1) / D)``, rad."""
    return np.arcsin((np.asarray(d2, dtype=float) - np.asarray(d1, dtype=float)) / separation)


def plane_chain(d1, d2, separation, ring_radius):
    """Eqs 4 and 9-19: every intermediate of the trigonometric chain.

    Parameters
    ----------
    d1, d2 : array_like
        Path lengths to R1 and R2, m.
    separation : float
        Receiver separation D, m.
    ring_radius : float
        Distance R from the emitter to the pair's mid-point, m.

    Returns
    -------
    dict of ndarray
        ``phi1, S, beta, gamma, y, delta, r, alpha, psi, theta`` (rad and m) --
        ``y = |T G|``, ``r = |T X|``, ``psi`` and ``theta`` the directions of X
        and G from the emitter in the pair frame.
    """
    d1 = np.asarray(d1, dtype=float)
    D, R = separation, ring_radius
    phi1 = bearing_eq4(d1, d2, D)
    S = np.sqrt(D**2 / 4 + R**2)  # (9)
    beta = np.arctan(D / (2 * R))  # (11)
    gamma = np.pi - phi1 + beta  # (10)
    y = np.sqrt(d1**2 + S**2 - 2 * d1 * S * np.cos(gamma)) / 2  # (13)
    delta = np.arcsin(S * np.sin(gamma) / (2 * y))  # (15)
    r = y / np.cos(delta)  # (16)
    alpha = np.arcsin(d1 * np.sin(gamma) / (2 * y))  # (18)
    psi = alpha - delta + beta  # (17)
    theta = alpha + beta  # (19)
    return dict(phi1=phi1, S=S, beta=beta, gamma=gamma, y=y, delta=delta, r=r, alpha=alpha, psi=psi, theta=theta)


def plane_point(d1, d2, separation, ring_radius):
    """Reflection point X of a plane seen by R1 (eqs 9-18), pair frame, shape (..., 2), m."""
    chain = plane_chain(d1, d2, separation, ring_radius)
    return chain["r"][..., None] * np.stack([np.cos(chain["psi"]), np.sin(chain["psi"])], axis=-1)


def corner_point(d1, d2, separation, ring_radius):
    """Corner point G from length y and angle theta (eq 19), pair frame, shape (..., 2), m."""
    chain = plane_chain(d1, d2, separation, ring_radius)
    return chain["y"][..., None] * np.stack([np.cos(chain["theta"]), np.sin(chain["theta"])], axis=-1)


def edge_solutions(d1, d2, separation, ring_radius):
    """Appendix A: both solutions ``(x, y, h)`` of eqs 21-24, in Browne's Fig. 8 frame.

    Parameters
    ----------
    d1, d2 : array_like
        Path lengths to R1 and R2, m.
    separation : float
        D = 2E, m.
    ring_radius : float
        R, m.

    Returns
    -------
    x1, y1, h1, x2, y2, h2 : ndarray
        Fig. 8 coordinates of the two candidate edges (origin between the
        receivers, R1 at y = -E) and their distances h = k from the emitter, m.
        NaN where the discriminant is negative (no real solution).
    """
    d_1 = np.asarray(d1, dtype=float)
    d_2 = np.asarray(d2, dtype=float)
    E = separation / 2
    R = ring_radius
    den = (8*d_2*d_1*R**2 - 4*d_2**2*R**2 - 4*d_1**2*R**2 - 8*E**2*d_2*d_1 + 16*R**2*E**2 - 4*E**2*d_2**2
           - 4*E**2*d_1**2)
    num = (-16*E**2*R**3 + 4*R**3*d_1**2 + 24*E**2*d_2*d_1*R - 4*E**2*d_1**2*R - 4*E**2*d_2**2*R
           + 8*R*d_2**2*d_1**2 + 16*E**4*R - 8*R**3*d_2*d_1 + 4*R**3*d_2**2 - 4*R*d_2**3*d_1 - 4*R*d_1**3*d_2)
    disc = (4*E**4*R**4*d_1**2 + 4*E**4*R**4*d_2**2 - 6*E**4*d_1**4*R**2 + 4*E**8*d_2**2 + E**4*d_2**6
            + E**4*d_1**6 + 4*E**8*d_1**2 + d_2**6*R**2*E**2 - 8*E**4*d_2*d_1**3*R**2 - 8*E**4*d_2**3*d_1*R**2
            - 4*E**4*d_2**2*d_1**2*R**2 - 6*E**4*d_2**4*R**2 + d_1**6*R**2*E**2 + 3*E**4*d_2**4*d_1**2
            + 8*E**4*d_2**3*d_1**3 + 8*E**8*d_2*d_1 + 3*E**4*d_2**2*d_1**4 - d_2**4*E**2*R**2*d_1**2
            + 16*E**6*d_2*d_1*R**2 + 8*E**4*R**4*d_2*d_1 - d_2**6*E**2*d_1**2 + 2*d_2**4*E**2*d_1**4
            - 5*E**6*d_2**4 - 5*E**6*d_1**4 + 2*R**4*E**2*d_2**2*d_1**2 - R**2*E**2*d_2**2*d_1**4
            + 8*E**6*d_2**2*R**2 + 8*E**6*d_1**2*R**2 - 8*E**6*d_1**3*d_2 - 8*E**6*d_2**3*d_1
            - 6*E**6*d_2**2*d_1**2 - R**4*E**2*d_2**4 - R**4*E**2*d_1**4 - E**2*d_1**6*d_2**2)
    with np.errstate(invalid="ignore"):
        root = disc**(1/2)
    solutions = []
    for branch in (num + 4*root, num - 4*root):
        x = 1/2/den*branch
        y = -1/2*(d_2**2*d_1 - d_2*R/den*branch - d_2*d_1**2 + E**2*d_2 - R**2*d_2 + d_1*R/den*branch - d_1*E**2
                  + R**2*d_1)/(d_1 + d_2)/E
        h = -1/2*(-2*R/den*branch - d_2**2 - d_1**2 + 2*E**2 - 2*R**2)/(d_1 + d_2)
        solutions += [x, y, h]
    return tuple(solutions)


def edge_point(d1, d2, separation, ring_radius):
    """Appendix A edge, the solution "real and in front of the receivers", pair frame, (..., 2), m.

    Browne: "the value of x must always be positive ... this is sufficient to
    select the correct solution".  Where both solutions have x > 0 the first is
    taken; where neither does the result is NaN.
    """
    x1, y1, _, x2, y2, _ = edge_solutions(d1, d2, separation, ring_radius)
    first = x1 > 0
    x = np.where(first, x1, np.where(x2 > 0, x2, np.nan))
    y = np.where(first, y1, y2)
    return np.stack([x + ring_radius, -y], axis=-1)


def vertical_eq26(t, h, ring_radius):
    """Eq 26: Browne's range estimate ``d = (sqrt(t^2 - h^2) - R) / 2`` for a vertical plane.

    ``t`` is the measured path, ``h`` the emitter-to-receiver height difference
    of the tier, ``R`` the ring radius (all m); ``d`` is the distance from the
    receivers to the plane, derived from the unfolded triangle of Fig. 11,
    ``(R + 2d)^2 = t^2 - h^2`` (eq 25).
    """
    t = np.asarray(t, dtype=float)
    return (np.sqrt(t**2 - h**2) - ring_radius) / 2
