"""The air's speed of sound, estimated from the map: what a wrong assumed speed leaves in a ring's sightings.

Every path is a time of flight times the speed of sound the nodes assume; if
the air's is ``1 + e`` times that, every true path is ``1 + e`` times the
measured one.  Were the sensor (its receivers and emitter) scaled by the same
factor, the whole scene would be: the map would come out scaled by ``1 / (1 +
e)`` about where it started and nothing could tell.  It is not: a ring's pair
solves its landmark from two paths and the receivers' and emitter's true
positions, so the landmark moves with the paths' scale as

    ``q(e) = q + e a``,  ``a = J d`` (``J = dq/dd``: :func:`sonar_ring.uncertainty.position_jacobian`; ``d`` the paths),

which is mostly the scaling ``e q`` (what the map takes up: the map is scaled)
and, across the line of sight, about ``e tan(theta)`` of bearing, ``theta`` the
landmark's angle off the pair's axis (0.04 deg at 10 deg for 2 K of air, ``e`` =
0.35 %): pairs that see one reflector at different angles disagree on its
bearing by that much.  Only the bearing is used: a range's share (the pair's
offset from the emitter times ``e``) is also what a fixed delay of the
receivers gives.

Each sighting ``i`` of map entry ``j`` measures ``y_i = h_i . mu_j - e s_i``
with variance ``v_i`` (:meth:`AirSpeed.add`): a wall's line angle (``h = (1,
0)``, ``mu`` the wall's angle), a corner's position across the line of sight
(``h`` the unit vector across it, ``mu`` the corner); ``s_i`` is the stretch
``a`` across the line of sight.  The entry's true ``mu_j`` is not needed: per
entry, only what its sightings disagree on enters the fit (their sums less the
part a common ``mu_j`` explains, as :mod:`sonar_ring.curvature`'s separation),
so the map's estimates, fitted to the same sightings, never do:

    ``e = -sum_j (sum s y / v - m_j^T I_j^+ p_j) / (sum_j (sum s^2 / v - m_j^T I_j^+ m_j) + 1 / sigma_e^2)``

with ``I_j = sum h h^T / v``, ``m_j = sum h s / v``, ``p_j = sum h y / v`` and a prior of standard deviation
``sigma_e`` about the assumed air.  A bearing is 15 mrad a sighting at 1 us of timing noise, so ``e``
takes thousands of sightings: 0.06 % after a lap of Browne's ring in a room, 0.04 % after three.

Edges are left out: their sightings, in a world with no noise at all, gave
``e`` = +0.4 % (13 % of them 2 mm or more across the line of sight off their
edge, the same way each time; those of corners are as often off, but not so).

Frames and units: m; ``e`` a fraction.
"""

from __future__ import annotations

import math

import numpy as np


class AirSpeed:
    """The fit of ``e``, the air's speed of sound relative to the assumed, less one (module docstring).

    Parameters
    ----------
    prior_sigma : float
        Standard deviation of ``e`` before any sighting (0: the assumed air is taken as right, ``e`` stays 0).
    """

    def __init__(self, prior_sigma: float):
        if not (math.isfinite(prior_sigma) and prior_sigma >= 0.0):
            raise ValueError(f"AirSpeed: prior_sigma must be a finite number >= 0, got {prior_sigma!r}")
        self.prior_sigma = float(prior_sigma)
        self._slots: dict[int, int] = {}
        self._information = np.zeros((0, 2, 2))  # per entry: sum h h^T / v
        self._pulled = np.zeros((0, 2))  # sum h y / v
        self._moved = np.zeros((0, 2))  # sum h s / v
        self._normal = np.zeros(0)  # sum s^2 / v
        self._along = np.zeros(0)  # sum s y / v
        self.sightings = 0

    def add(self, entry, observes, measured, stretch, variance) -> None:
        """Add sightings ``y = h . mu - e s`` of the map's entries ``entry`` (n,).

        ``observes`` (n, 2) is ``h``; ``measured`` (n,) ``y``; ``stretch`` (n,) ``s``; ``variance`` (n,) ``v``,
        the units of ``y`` squared.  Rows with a non-finite value or a variance not above 0 are left out.
        """
        observes = np.asarray(observes, dtype=float)
        measured, stretch, variance = (np.asarray(v, dtype=float) for v in (measured, stretch, variance))
        usable = np.isfinite(observes).all(1) & np.isfinite(measured) & np.isfinite(stretch) & (variance > 0.0) \
            & np.isfinite(variance)
        if self.prior_sigma == 0.0 or not usable.any():
            return
        slot = self._slots_of(np.asarray(entry, dtype=np.int64)[usable])
        h, y, s, weight = observes[usable], measured[usable], stretch[usable], 1.0 / variance[usable]
        np.add.at(self._information, slot, weight[:, None, None] * h[:, :, None] * h[:, None, :])
        np.add.at(self._pulled, slot, (weight * y)[:, None] * h)
        np.add.at(self._moved, slot, (weight * s)[:, None] * h)
        np.add.at(self._normal, slot, weight * s * s)
        np.add.at(self._along, slot, weight * s * y)
        self.sightings += int(slot.size)

    def start_session(self) -> None:
        """Entries from now on are new ones, whatever their ids (a new map session numbers its own from 0).

        What the entries before gave stays in the fit.
        """
        self._slots.clear()

    def forget(self, entries) -> None:
        """Drop what the entries ``entries`` gave (a ghost's sightings are not of a fixed reflector)."""
        for entry in np.asarray(entries, dtype=np.int64).tolist():
            slot = self._slots.pop(entry, None)
            if slot is not None:
                for array in (self._information, self._pulled, self._moved, self._normal, self._along):
                    array[slot] = 0.0

    def fit(self) -> tuple[float, float]:
        """``(e, sigma_e)``: the estimate and its standard deviation; ``(0, prior_sigma)`` before any sighting."""
        if self.prior_sigma == 0.0:
            return 0.0, 0.0
        inverse = _pseudo_inverse(self._information)
        normal = np.sum(self._normal - np.einsum("ni,nij,nj->n", self._moved, inverse, self._moved))
        along = np.sum(self._along - np.einsum("ni,nij,nj->n", self._moved, inverse, self._pulled))
        information = float(normal) + 1.0 / self.prior_sigma ** 2
        return 0.0 - float(along) / information, 1.0 / math.sqrt(information)  # 0.0 -: never a negative zero

    def _slots_of(self, entry: np.ndarray) -> np.ndarray:
        """Each entry's row in the sums, new rows for new entries."""
        new = [e for e in dict.fromkeys(entry.tolist()) if e not in self._slots]
        if new:
            first = len(self._normal)
            self._slots.update({e: first + k for k, e in enumerate(new)})
            self._information = np.concatenate([self._information, np.zeros((len(new), 2, 2))])
            self._pulled = np.concatenate([self._pulled, np.zeros((len(new), 2))])
            self._moved = np.concatenate([self._moved, np.zeros((len(new), 2))])
            self._normal = np.concatenate([self._normal, np.zeros(len(new))])
            self._along = np.concatenate([self._along, np.zeros(len(new))])
        return np.array([self._slots[e] for e in entry.tolist()], dtype=np.int64)


def _pseudo_inverse(matrix: np.ndarray) -> np.ndarray:
    """Moore-Penrose inverses of symmetric positive semi-definite (n, 2, 2) matrices, in closed form.

    An entry seen along one direction only (a wall's angle; a corner from one side) has a rank-1 sum
    ``M = u u^T t``, whose pseudo-inverse is ``M / trace(M)^2``; ``numpy.linalg.pinv``'s SVD of every entry
    cost more than the rest of the fit.
    """
    a, b, c = matrix[:, 0, 0], matrix[:, 0, 1], matrix[:, 1, 1]
    trace, determinant = a + c, a * c - b * b
    full = determinant > 1e-9 * trace ** 2
    inverse = np.zeros_like(matrix)
    with np.errstate(divide="ignore", invalid="ignore"):
        adjugate = np.stack([np.stack([c, -b], -1), np.stack([-b, a], -1)], -2)
        inverse[full] = adjugate[full] / determinant[full, None, None]
        single = ~full & (trace > 0.0)
        inverse[single] = matrix[single] / (trace[single] ** 2)[:, None, None]
    return inverse
