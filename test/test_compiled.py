"""Tests of the numba kernels' mechanics (sonar_ring.compiled); their numbers are tested with their modules."""

import numba
import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from sonar_ring import localise, mapping


def test_a_kernel_becomes_its_dispatcher_and_matches_its_python_source():
    matrices = np.array([[[2.0, 1.0], [1.0, 3.0]], [[4.0, -1.0], [-1.0, 0.5]]])
    inverse = mapping._inverse(matrices)
    assert_allclose(inverse @ matrices, np.broadcast_to(np.eye(2), (2, 2, 2)), atol=1e-15)
    # Every kernel of every module is now the compiled dispatcher itself, and the
    # machine code gives exactly what the Python source gives.
    for function in (mapping._inverse, mapping._sandwich, localise.solve_rows):
        assert isinstance(function, numba.core.registry.CPUDispatcher)
    assert_array_equal(mapping._inverse(matrices), mapping._inverse.py_func(matrices))


def test_kernels_call_kernels():
    """_match_walls calls _inverse, _sandwich, _line_floor and _mahalanobis2 as compiled code."""
    anchor = np.array([[0.0, 1.0], [0.5, 1.01]])
    line = np.zeros((2, 2))
    information = np.tile(np.diag([1e4, 1e6]), (2, 1, 1))
    normal = np.tile([0.0, 1.0], (2, 1))
    tangent = np.tile([-1.0, 0.0], (2, 1))
    extent = np.array([[-0.2, 0.2], [-0.2, 0.2]])
    keep, other = np.array([0]), np.array([1])
    compiled = mapping._match_walls(keep, other, anchor, line, information, normal, tangent, extent, 0.001)
    python = mapping._match_walls.py_func(keep, other, anchor, line, information, normal, tangent, extent, 0.001)
    for a, b in zip(compiled, python, strict=True):
        assert_array_equal(a, b)
    assert_allclose(compiled[2], [[0.0, 0.01]], atol=1e-15)  # innovation: same angle, 1 cm apart


def test_error_handling():
    # IEEE division, as numpy: a singular matrix gives inf and NaN, not ZeroDivisionError.
    inverse = mapping._inverse(np.zeros((1, 2, 2)))
    assert np.all(~np.isfinite(inverse))
    # Arguments of the wrong kind are refused by the type checker, with the kernel named.
    with pytest.raises(numba.core.errors.TypingError, match="_inverse"):
        mapping._inverse("not an array")
