"""What an engineer would write without the closed forms: one ``scipy.optimize.least_squares`` per echo.

For a plane or a corner the unknown is the virtual image ``T'`` with residuals
``|T' - R_n| - d_n``; the plane's reflection point X seen by R1 is then where
the segment ``R1 T'`` meets the perpendicular bisector of ``T T'``, the corner
``(T + T') / 2``.  For an edge the unknown is the point ``P`` with residuals
``|P - T| + |P - R_n| - d_n``.  Each fit starts from the conventional ranger's
point on the pair's axis (:func:`sonar_ring.localise.on_axis`; for ``T'`` its
mirror image through the emitter's side) and uses the defaults of
``least_squares`` (trust-region reflective, finite-difference Jacobian,
tolerances 1e-8).  A fit is valid when it reports success and lands in front
of the receivers.  scipy is imported when a fit is run: it is a test and
benchmark dependency, not one of the package.
"""

from __future__ import annotations

import numpy as np

from sonar_ring import localise as loc
from sonar_ring.benchmark.methods import Batch

MODELS = ("plane", "corner", "edge")


def fit(model: str, batch: Batch):
    """Least-squares estimates of ``model`` for every echo of ``batch``, one call per echo.

    Parameters
    ----------
    model : str
        ``"plane"`` (R1's reflection point), ``"corner"`` or ``"edge"``.
    batch : Batch
        Echoes with their horizontal paths.

    Returns
    -------
    point : ndarray, shape (N, 2)
        Estimates, m, sensor frame (NaN where the fit failed).
    valid : ndarray of bool, shape (N,)
    """
    from scipy.optimize import least_squares

    if model not in MODELS:
        raise ValueError(f"least_squares.fit: model must be one of {MODELS}, got {model!r}")
    rows = batch.rows
    ranger = loc.on_axis(rows.tx, rows.rx1, rows.rx2, batch.d1, batch.d2).position
    start = ranger if model == "edge" else 2.0 * ranger - rows.tx
    point = np.full((len(batch), 2), np.nan)
    valid = np.zeros(len(batch), dtype=bool)
    for n in range(len(batch)):
        tx, receivers, paths = rows.tx[n], np.stack([rows.rx1[n], rows.rx2[n]]), batch.horizontal[n]
        if model == "edge":
            def residuals(p, tx=tx, receivers=receivers, paths=paths):
                return np.hypot(*(p - tx)) + np.hypot(*(p - receivers).T) - paths
        else:
            def residuals(p, receivers=receivers, paths=paths):
                return np.hypot(*(p - receivers).T) - paths
        if not np.all(np.isfinite(start[n])):
            continue
        solution = least_squares(residuals, start[n])
        estimate = solution.x
        if model == "corner":
            estimate = 0.5 * (tx + estimate)
        elif model == "plane":
            estimate = _reflection_point(tx, receivers[0], estimate)
        middle = receivers.mean(axis=0)
        front = np.dot(estimate - middle, middle - tx) > 0
        if solution.success and front and np.all(np.isfinite(estimate)):
            point[n], valid[n] = estimate, True
    return point, valid


def _reflection_point(tx, receiver, image):
    """Where the segment from ``receiver`` to the virtual image crosses the bisector of ``tx`` and ``image``."""
    towards = image - receiver
    # |X - T| = |X - T'| for X = R + f (T' - R) is linear in f.
    fraction = (np.dot(towards, towards) - np.dot(receiver - tx, receiver - tx)) / (
        2.0 * np.dot(towards, image - tx))
    return receiver + fraction * towards
