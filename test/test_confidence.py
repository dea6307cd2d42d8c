"""A decision's confidence from its margin (sonar_ring.confidence)."""

import math

import numpy as np
from numpy.testing import assert_allclose, assert_array_equal

from sonar_ring.confidence import confidence_from_margin


def test_confidence_is_the_gaussian_mass_within_the_margin():
    margins = np.array([0.0, 0.5, 1.0, 2.0, 3.0, 6.0])
    expected = [math.erf(m / math.sqrt(2)) for m in margins]
    assert_allclose(confidence_from_margin(margins), expected, atol=2e-7)
    assert_array_equal(confidence_from_margin([-1.0, np.nan]), [0.0, 0.0])
    flat = confidence_from_margin(margins)
    for grid in (margins.reshape(2, 3), margins.reshape(3, 2).T):  # any shape and memory order, kept
        assert_array_equal(confidence_from_margin(grid), flat[np.searchsorted(margins, grid)])
    assert confidence_from_margin(3.0).shape == ()
