"""Loops of the core compiled with numba, where numpy's cost per call is the cost.

A ping holds tens to hundreds of echoes, each with a handful of receivers, and the
map holds 2 x 2 matrices per entry: there numpy spends its time starting each
operation, not computing (about 1 us per call on arrays of 30 elements).  The few
loops that dominate a ping are plain Python over arrays, compiled by
:func:`kernel` at their first call:

* numba is imported then, not when the core is imported (about 0.2 s and 100 MiB a
  process that never calls a kernel need not pay);
* the machine code is cached beside the module (or in the user's cache where that
  is read-only), so later processes load it in tens of milliseconds;
* ``error_model="numpy"``: division follows IEEE (inf and NaN, as numpy) instead of
  raising ``ZeroDivisionError``.

Each kernel is the only implementation of its computation; its Python source stays
readable and is what the tests exercise, compiled.
"""

from __future__ import annotations

import functools


def kernel(function):
    """``function`` compiled with numba (nopython, cached, IEEE division) at its first call."""
    compiled = None

    @functools.wraps(function)
    def call(*args):
        nonlocal compiled
        if compiled is None:
            import numba

            compiled = numba.njit(cache=True, error_model="numpy", nogil=True)(function)
        return compiled(*args)

    return call
