"""Loops of the core compiled with numba, where numpy's cost per call is the cost.

A ping holds tens to hundreds of echoes, each with a handful of receivers, and the
map holds 2 x 2 matrices per entry: there numpy spends its time starting each
operation, not computing (doc/CORE_API.md, "The numpy core", has the figures).  The few
loops that dominate a ping are plain Python over arrays, marked :func:`kernel`
and compiled from the first call of any kernel on:

* numba is imported then, not when the core is imported (its start-up time and
  memory are for processes that call a kernel);
* every kernel becomes its numba dispatcher, under its own name in its module,
  so kernels call each other as compiled code and Python callers reach the
  machine code without a wrapper.  A kernel calls kernels of its own module
  only: numba's cache of a caller holds its callees' code and is invalidated by
  changes to the caller's file alone;
* the machine code is cached beside the module (or in the user's cache where that
  is read-only; nowhere, and compiled in each process, where neither can be
  written), so later processes load it instead of compiling it;
* ``error_model="numpy"``: division follows IEEE (inf and NaN, as numpy) instead of
  raising ``ZeroDivisionError``;
* ``kernel(inline=True)`` inlines a kernel into its callers before they are
  compiled: LLVM inlines small kernels by itself, not one the size of a whole
  model's solution, whose call per entry would then slow the caller's loop; and
  a compiled call that passes arrays counts each one's references up and down
  with atomic instructions, which LLVM's inlining leaves in place (11 % of
  :func:`sonar_ring.image_method.map_paths`' time, whose helpers are inlined for
  that, at 20 s more to compile the kernels the first time: 74 -> 95 s).

Each kernel is the only implementation of its computation; its Python source stays
readable and is what the tests exercise, compiled.
"""

from __future__ import annotations

import functools
import sys
import threading

_KERNELS: dict[str, list] = {}
"""The kernel functions of each module, by module name, in definition order, each with its numba options."""
_DISPATCHERS: dict[tuple, object] = {}
"""The numba dispatcher of each kernel compiled so far, by (module name, function name)."""
_LOCK = threading.Lock()


def kernel(function=None, *, inline: bool = False):
    """Mark ``function`` (module level) for numba: compiled (nopython, cached, IEEE division) at first use.

    ``@kernel`` or ``@kernel(inline=True)``: the latter is compiled into each
    kernel that calls it instead of being called.
    """
    if function is None:
        return functools.partial(kernel, inline=inline)
    _KERNELS.setdefault(function.__module__, []).append((function, {"inline": "always"} if inline else {}))

    @functools.wraps(function)
    def first_call(*args, **kwargs):
        return _compile()[function.__module__, function.__name__](*args, **kwargs)

    return first_call


def _compile() -> dict:
    """Every kernel of every imported module as a numba dispatcher, put in its module under its name.

    All at once, so a kernel may call the others of its module; numba compiles
    (or loads) each one at its own first call.  Kernels of modules imported later
    join at the next first call.
    """
    import numba

    with _LOCK:
        for module_name, functions in list(_KERNELS.items()):
            for function, own_options in functions:
                if (module_name, function.__name__) in _DISPATCHERS:
                    continue
                options = {"error_model": "numpy", "nogil": True, **own_options}
                try:
                    dispatcher = numba.njit(cache=True, **options)(function)
                except RuntimeError:  # no writable cache location: compile in each process instead
                    dispatcher = numba.njit(**options)(function)
                _DISPATCHERS[module_name, function.__name__] = dispatcher
                setattr(sys.modules[module_name], function.__name__, dispatcher)
        return _DISPATCHERS
