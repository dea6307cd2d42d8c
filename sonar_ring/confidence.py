"""A decision's confidence from the margin by which its test passed: ``2 Phi(m) - 1``.

Both kinds of class evidence -- Barshan & Kuc's amplitude rules
(:mod:`sonar_ring.amplitude_rules`) and the ring's geometric consistency
(:mod:`sonar_ring.ring_consistency`) -- return a class code, the *margin*
``m`` by which the deciding test passed its threshold, in standard deviations
of the tested statistic, and this confidence in [0, 1] (``Phi`` the standard
normal distribution): 0 at the threshold and whenever no decision is made,
0.68 one standard deviation beyond it, 0.95 two, 0.997 three.  A landmark
carries it (``Landmarks.confidence``).
"""

from __future__ import annotations

import numpy as np

from sonar_ring.compiled import kernel


def confidence_from_margin(margin):
    """Confidence in [0, 1] from a test margin in standard deviations: ``2 Phi(m) - 1``.

    ``erf(m / sqrt(2))``, the probability that a standard normal deviate lies within
    ``+-m``; evaluated with Abramowitz & Stegun 7.1.26 (absolute error < 2e-7),
    compiled (:func:`_confidence`).  Margins <= 0 or NaN give 0.

    Parameters
    ----------
    margin : array_like
        Margins, standard deviations.

    Returns
    -------
    ndarray
        Confidences, same shape.
    """
    margin = np.array(margin, dtype=float, order="C")  # a copy: writable and contiguous, one type to numba
    return _confidences(margin.reshape(-1)).reshape(margin.shape)


@kernel
def _confidences(margin):
    """:func:`_confidence` of each margin of a flat array (N,)."""
    confidence = np.empty(margin.size)
    for n in range(margin.size):
        confidence[n] = _confidence(margin[n])
    return confidence


@kernel
def _confidence(margin):
    """:func:`confidence_from_margin` of one margin."""
    x = margin / np.sqrt(2.0)
    if not x > 0:  # also NaN
        return 0.0
    t = 1.0 / (1.0 + 0.3275911 * x)
    poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429))))
    return 1.0 - poly * np.exp(-x * x)


def load_kernels() -> None:
    """Load the compiled confidence now instead of at the first decision (the localiser node, at start)."""
    confidence_from_margin(np.zeros(1))
