"""Edge or corner: the wavefront's curvature, seen over motion, from a fixed point's sightings.

A convex edge re-radiates from a point ``P``: the path to receiver ``R`` is
``|P - T| + |P - R|``.  A concave right-angle corner reflects the emitter's image:
the path is ``|2C - T - R|``.  For ``C = P`` the two differ by a second-order
term (they agree when ``T``, ``R`` and the point are collinear): 0.1-0.7 mm for
Browne's ring at 0.6-3 m.  A ping cannot use that much (the path noise is
0.35 mm at 1 us, and the speed of sound scales every path alike), but it moves
the position the ring's pair computes: the two models, solved from the same
two paths, put a point up to about a degree apart *across* the line of sight
(and 0.1 mm along it), by an amount and direction that change with the
viewpoint.  Seen from many poses, a fixed point's sightings are consistent
under the model that is true, and scatter under the other.

:func:`point_models` gives both models' positions for every point sighting
of a single-emitter ring, from the paths its landmark implies (the class's own
model, inverted).  The map (:class:`~sonar_ring.mapping.LandmarkMap`) keeps,
per point, both models' information-weighted fits over its sightings and
their residual sums ``chi2_corner``, ``chi2_edge``; with
``Delta = chi2_corner - chi2_edge`` (twice the log ratio of the maximised
likelihoods) and the two models' separation

    ``lambda = sum d_i^T W_i d_i - (sum W_i d_i)^T (sum W_i)^-1 (sum W_i d_i)``

(``d_i`` the difference of sighting i's two positions, ``W_i`` its inverse
covariance: the part of the models' difference no common offset explains, and
the value ``Delta`` takes on average under either model; less what the
paths' noise alone adds to it, ``PointModels.separation_noise``), a point is an EDGE
when ``Delta >= threshold``, a CORNER when ``Delta <= -threshold``, once
``lambda >= min_separation`` (a sequential test; documented with the map's
parameters).  ``lambda`` grows with each sighting from a new angle: the
distance driven until a decision is that of the sightings that give it.
A point seen only head-on (``T``, ``R`` and it collinear: no curvature) keeps
``lambda`` near zero and stays CORNER_OR_EDGE.  So does every fixed point of a
Kreczmer triad: its emitter sits within 7.5 mm of its receivers, so the two
models' paths differ by 1-30 um at 0.5-2 m (the path noise: 0.34 mm at 1 us),
and :func:`point_models` gives it none.

Frames and units: the landmarks' frame (sensor frame per ping), m.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sonar_ring import solvers
from sonar_ring.geometry import Layout
from sonar_ring.landmarks import CORNER, EDGE, UNKNOWN, Landmarks
from sonar_ring.poses import turned_covariances

CURVATURE_THRESHOLD = 13.816
"""``|chi2_corner - chi2_edge|`` that tells a fixed point an edge or a corner: ``2 ln 1000``, a likelihood ratio of
1000:1 (a sequential test that stops there is wrong at most once in a thousand, Wald)."""

CONSISTENCY_Z = 3.0902
"""Standard normal 99.9 % point: a model must fit by itself, its chi-square below this quantile."""


def chi2_quantile(dof, z: float):
    """Wilson-Hilferty approximation of the chi-square quantile of ``dof`` degrees of freedom at normal point ``z``."""
    dof = np.maximum(dof, 1.0)
    k = 2.0 / (9.0 * dof)
    return dof * (1.0 - k + z * np.sqrt(k)) ** 3


def decide(corner_chi2, edge_chi2, separation, sightings, threshold: float, min_separation: float):
    """Which fixed points their curvature tells an edge or a corner (module docstring); arrays (P,).

    Parameters
    ----------
    corner_chi2, edge_chi2 : array_like
        Each model's residual sum over a point's sightings.
    separation : array_like
        The models' separation ``lambda``.
    sightings : array_like of int
        Sightings in the fits (``2 (n - 1)`` degrees of freedom each).
    threshold, min_separation : float
        ``|Delta|`` and ``lambda`` needed.

    Returns
    -------
    edge, corner : ndarray of bool
        Told an edge (``Delta >= threshold``) or a corner (``Delta <= -threshold``), where
        ``lambda >= min_separation`` and the winner's chi-square lies below its 99.9 % point.
    confidence : ndarray
        ``1 - exp(-|Delta| / 2)``.
    """
    delta = np.asarray(corner_chi2, dtype=float) - np.asarray(edge_chi2, dtype=float)
    winner = np.minimum(corner_chi2, edge_chi2)
    dof = 2.0 * (np.asarray(sightings, dtype=float) - 1.0)
    decided = ((np.asarray(separation) >= min_separation) & (np.abs(delta) >= threshold)
               & (winner <= chi2_quantile(dof, CONSISTENCY_Z)))
    return decided & (delta > 0), decided & (delta < 0), 1.0 - np.exp(-0.5 * np.abs(delta))


@dataclass(frozen=True)
class PointModels:
    """Both models' positions of L point sightings, each with its own covariance.

    The two positions are functions of the same two paths, with different
    gains: each model's chi-square over a point's sightings, taken with its
    own covariance, is its likelihood in the paths' space (the change of
    variables cancels), so their difference is the log-likelihood ratio.

    Attributes
    ----------
    corner, edge : ndarray, shape (L, 2)
        The virtual-image (corner) model's and the edge model's position, m;
        NaN where not ``valid``.
    corner_covariance, edge_covariance : ndarray, shape (L, 2, 2)
        Each position's covariance from the paths' noise, m^2 (without the
        edge/corner discrepancy an undecided landmark's covariance carries).
    separation_noise : ndarray, shape (L,)
        ``tr(W D)``: the part of a sighting's share ``d^T W d`` of the
        separation that the paths' noise alone gives on average (``D`` the
        covariance of the models' difference ``d``, ``W`` the corner model's
        weight); the map subtracts it, so that ``lambda`` grows with new
        viewpoints and not with pings from the same one.
    valid : ndarray of bool, shape (L,)
        Where both models have a solution (a point sighting of a single-emitter ring).
    """

    corner: np.ndarray
    edge: np.ndarray
    corner_covariance: np.ndarray
    edge_covariance: np.ndarray
    separation_noise: np.ndarray
    valid: np.ndarray

    def transformed(self, pose) -> PointModels:
        """The same models in the frame where the landmarks' frame sits at ``pose`` ``(x, y, yaw)``."""
        c, s = np.cos(pose[2]), np.sin(pose[2])
        rotation = np.array([[c, -s], [s, c]])
        return PointModels(self.corner @ rotation.T + pose[:2], self.edge @ rotation.T + pose[:2],
                           turned_covariances(self.corner_covariance, rotation),
                           turned_covariances(self.edge_covariance, rotation),
                           self.separation_noise, self.valid)

    def widened(self, extra) -> PointModels:
        """The same models with ``extra`` (2, 2) or (L, 2, 2), m^2, added to both covariances."""
        return PointModels(self.corner, self.edge, self.corner_covariance + extra, self.edge_covariance + extra,
                           self.separation_noise, self.valid)

    def select(self, rows) -> PointModels:
        """The sightings ``rows`` (an index array or a mask)."""
        return PointModels(self.corner[rows], self.edge[rows], self.corner_covariance[rows],
                           self.edge_covariance[rows], self.separation_noise[rows], self.valid[rows])


def point_models(layout: Layout, landmarks: Landmarks, rows=None) -> PointModels:
    """Both models' positions of each point sighting of a single-emitter ring, from the paths it implies.

    An UNKNOWN or CORNER landmark was placed by the virtual-image model: its
    virtual image is ``T' = 2G - T`` and its horizontal paths ``|T' - R_k|``;
    an EDGE landmark by the edge model: ``|P - T| + |P - R_k|``.  Both models
    are solved again from those paths (the closed forms of
    :func:`sonar_ring.localise.corner` and :func:`~sonar_ring.localise.edge`).
    The paths' covariance is recovered from the landmark's (less the
    discrepancy ``g g^T``, ``g`` the models' difference, that
    :func:`sonar_ring.pipeline.classify_ping` adds to an UNKNOWN landmark's)
    through its model's Jacobian, and carried to each model through that
    model's (:func:`sonar_ring.uncertainty.position_jacobian`), plus the arc's
    second-order spread.  One compiled loop over the sightings
    (:func:`sonar_ring.solvers.point_model_rows`): the mapper calls this for
    every ping.

    Parameters
    ----------
    layout : Layout
        The sensor; other kinds than a ring give no models (all invalid): a
        triad's fixed points stay CORNER_OR_EDGE (module docstring), a pair's
        have the amplitude rules.
    landmarks : Landmarks
        L labelled landmarks of one ping, sensor frame.
    rows : array_like of bool, shape (L,), optional
        Only these landmarks (the others get no models); default all.

    Returns
    -------
    PointModels
    """
    if layout.kind != "ring":
        count = len(landmarks)
        return PointModels(np.full((count, 2), np.nan), np.full((count, 2), np.nan),
                           np.full((count, 2, 2), np.nan), np.full((count, 2, 2), np.nan), np.zeros(count),
                           np.zeros(count, bool))
    kind = np.asarray(landmarks.landmark_class)
    chosen = np.asarray(landmarks.valid, dtype=bool) & ((kind == UNKNOWN) | (kind == CORNER) | (kind == EDGE))
    if rows is not None:
        chosen &= np.asarray(rows, dtype=bool)
    # Copies (np.array) in the types load_kernels compiled, whatever arrays the caller's landmarks hold (a
    # read-only one is another type to numba).
    return PointModels(*solvers.point_model_rows(
        chosen, np.array(landmarks.group, dtype=np.int64), layout.plan.transmitters, layout.plan.receivers,
        np.array(landmarks.position, dtype=float), kind == EDGE, kind == UNKNOWN,
        np.array(landmarks.covariance, dtype=float)))


def load_kernels() -> None:
    """Load :func:`point_models`' compiled loop now instead of at the first ping, with the production argument types.

    One sighting of a point 1 m in front of the first pair of a ring (whose plan's arrays are read-only, a type
    of their own to numba).
    """
    from sonar_ring.geometry import load_layout

    plan = load_layout("browne_ring").plan
    solvers.point_model_rows(np.ones(1, dtype=bool), np.zeros(1, dtype=np.int64), plan.transmitters, plan.receivers,
                             np.array([[1.0, 0.0]]), np.zeros(1, dtype=bool), np.ones(1, dtype=bool),
                             np.tile(1e-6 * np.eye(2), (1, 1, 1)))
