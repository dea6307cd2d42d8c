"""Uncertainty of the localisation: the paths' covariance, and what it makes of an estimate's position.

* :func:`path_covariance` -- the covariance of the two measured paths from the
  times of flight's noise and the speed of sound's;
* :func:`position_jacobian` and :func:`position_covariance` -- its first-order
  image in an estimate of :mod:`sonar_ring.localise` (the pipeline's
  fallback where the unscented transform of :mod:`sonar_ring.solvers` loses a
  sigma point);
* :func:`cramer_rao_bound` -- the bounds any estimator of one pair meets
  (its docstring gives them).

Units and frames as in :mod:`sonar_ring.localise`: metres, seconds, one frame
for every position.
"""

from __future__ import annotations

import math

import numpy as np

from sonar_ring import solvers
from sonar_ring.checks import broadcast_shape, flat_copies, points, quiet, real_array
from sonar_ring.localise import PointEstimate


def cramer_rao_bound(separation, sigma_tof, speed_of_sound, phi=0.0):
    """Cramer-Rao bounds on bearing and range for one pair.

    ``sigma_phi >= sqrt(2) c sigma_t / (D cos phi)`` and
    ``sigma_r >= c sigma_t / (2 sqrt(2))``, for independent TOF noise of standard
    deviation ``sigma_t`` on both receivers and a transmitter at the pair's
    mid-point (range = half the mean path).  Far-field bounds: the exact ones
    differ by O(D / range).

    Parameters
    ----------
    separation : array_like
        Receiver separation D, m.
    sigma_tof : array_like
        Standard deviation of each time of flight, s.
    speed_of_sound : array_like
        c, m/s.
    phi : array_like
        Bearing, rad.

    Returns
    -------
    sigma_bearing, sigma_range : ndarray
        Lower bounds on the standard deviations, rad and m.
    """
    sigma_path = np.asarray(speed_of_sound, dtype=float) * np.asarray(sigma_tof, dtype=float)
    sigma_bearing = np.sqrt(2.0) * sigma_path / (np.asarray(separation, dtype=float) * np.cos(phi))
    return sigma_bearing, sigma_path / (2.0 * np.sqrt(2.0))


def path_covariance(d1, d2, sigma_tof, speed_of_sound, sigma_speed=0.0) -> np.ndarray:
    """Covariance of the path lengths ``(d1, d2)`` from TOF and speed-of-sound noise.

    ``d_n = c tof_n``: independent TOF errors of standard deviation ``sigma_tof``
    give ``(c sigma_tof)^2`` on the diagonal; an error ``dc`` of the speed of
    sound, common to both receivers, moves both paths by ``d_n dc / c``.

    Parameters
    ----------
    d1, d2 : array_like, shape (...)
        Path lengths, m.
    sigma_tof : array_like, shape (...)
        Standard deviation of each TOF, s (>= 0).
    speed_of_sound : array_like, shape (...)
        c, m/s (> 0).
    sigma_speed : array_like, shape (...)
        Standard deviation of c, m/s (>= 0).

    Returns
    -------
    ndarray, shape (..., 2, 2)
        Covariance, m^2.

    Raises
    ------
    ValueError
        If a noise parameter is negative or not finite, or c <= 0 (these are
        configuration, not data).
    """
    d1 = real_array("d1", d1, "path_covariance")
    d2 = real_array("d2", d2, "path_covariance")
    sigma_tof = real_array("sigma_tof", sigma_tof, "path_covariance")
    speed = real_array("speed_of_sound", speed_of_sound, "path_covariance")
    sigma_speed = real_array("sigma_speed", sigma_speed, "path_covariance")
    check_path_noise(sigma_tof, speed, sigma_speed, "path_covariance")
    shape = broadcast_shape("path_covariance", d1=d1, d2=d2, sigma_tof=sigma_tof, speed=speed,
                            sigma_speed=sigma_speed)
    return solvers.path_covariance_rows(*flat_copies(shape, d1, d2, sigma_tof, speed, sigma_speed)).reshape(
        shape + (2, 2))


def check_path_noise(sigma_tof, speed_of_sound, sigma_speed, caller: str) -> None:
    """Refuse the noise parameters of a paths' covariance that make no sense, with ``ValueError``.

    All must be finite, ``sigma_tof`` (s) and ``sigma_speed`` (m/s) >= 0 and
    ``speed_of_sound`` (m/s) > 0; arrays or scalars.
    """
    lowest = [_lowest_finite(value) for value in (sigma_tof, speed_of_sound, sigma_speed)]
    if not (lowest[0] >= 0 and lowest[1] > 0 and lowest[2] >= 0):
        raise ValueError(f"{caller}: need sigma_tof >= 0, sigma_speed >= 0 and speed_of_sound > 0, all finite")


def _lowest_finite(value) -> float:
    """The smallest of a number or array (inf when empty: nothing to refuse), NaN when any is not finite."""
    if isinstance(value, float | int):
        # A ping's settings are numbers: checked without numpy, whose reductions cost more than the check.
        return value if math.isfinite(value) else math.nan
    array = np.asarray(value, dtype=float)
    if not array.size:
        return math.inf
    return float(array.min()) if np.isfinite(array).all() else math.nan


@quiet
def position_jacobian(estimate: PointEstimate, tx, rx1, rx2) -> np.ndarray:
    """Derivative of an estimate's position with respect to the paths ``(d1, d2)``.

    From the implicit equations of each model: the virtual image satisfies
    ``|T' - R_n| = d_n``, so ``dT'/dd = U^-1`` with rows ``(T' - R_n) / d_n``, and
    the plane foot point and the corner ``G = (T + T') / 2`` take half of it; an
    edge satisfies ``|P - T| + |P - R_n| = d_n``.

    Parameters
    ----------
    estimate : PointEstimate
        Result of :func:`~sonar_ring.localise.virtual_image`,
        :func:`~sonar_ring.localise.plane` (foot point), :func:`~sonar_ring.localise.corner`,
        :func:`~sonar_ring.localise.edge` or :func:`~sonar_ring.localise.on_axis`.
    tx, rx1, rx2 : array_like, shape (..., 2)
        The positions the estimate was computed with, m.

    Returns
    -------
    ndarray, shape (..., 2, 2)
        ``J[..., i, n] = d position_i / d d_n`` (dimensionless); +inf where the
        geometry is singular (an echo on the receivers' line), NaN where the
        estimate is not valid.
    """
    tx = points("tx", tx, "position_jacobian")
    rx1 = points("rx1", rx1, "position_jacobian")
    rx2 = points("rx2", rx2, "position_jacobian")
    if estimate.model not in solvers.SOLVERS:
        raise ValueError(f"position_jacobian: unknown model {estimate.model!r}")
    shape = broadcast_shape("position_jacobian", ("tx", "rx1", "rx2", "position"), tx=tx, rx1=rx1, rx2=rx2,
                            position=estimate.position)
    rows = [array.reshape(-1, 2) for array in flat_copies(shape + (2,), tx, rx1, rx2, estimate.position)]
    jacobian = solvers.jacobian_rows(solvers.SOLVERS.index(estimate.model), *rows).reshape(shape + (2, 2))
    return np.where(estimate.valid[..., None, None], jacobian, np.nan)


@quiet
def position_covariance(estimate: PointEstimate, tx, rx1, rx2, paths_covariance) -> np.ndarray:
    """First-order 2x2 covariance of an estimate's position: ``J S J^T``.

    Parameters
    ----------
    estimate : PointEstimate
        As for :func:`position_jacobian` (for a plane, the foot point).
    tx, rx1, rx2 : array_like, shape (..., 2)
        The positions the estimate was computed with, m.
    paths_covariance : array_like, shape (..., 2, 2)
        Covariance ``S`` of ``(d1, d2)``, m^2, e.g. from :func:`path_covariance`.

    Returns
    -------
    ndarray, shape (..., 2, 2)
        Covariance of the position, m^2; +inf where the geometry is singular,
        NaN where the estimate is not valid.
    """
    jacobian = position_jacobian(estimate, tx, rx1, rx2)
    paths_covariance = real_array("paths_covariance", paths_covariance, "position_covariance")
    if paths_covariance.shape[-2:] != (2, 2):
        raise ValueError(f"position_covariance: 'paths_covariance' must be (..., 2, 2), got {paths_covariance.shape}")
    covariance = jacobian @ paths_covariance @ np.swapaxes(jacobian, -1, -2)
    singular = np.isinf(jacobian).any(axis=(-1, -2))
    return np.where(singular[..., None, None] & estimate.valid[..., None, None], np.inf, covariance)
