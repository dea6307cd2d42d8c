"""Every localisation method of the benchmark behind one signature, grouped by family.

A :class:`Method` turns a :class:`Batch` of echoes into estimates and a
validity flag; a :class:`Family` says which echoes it is judged on and against
which truth.  The families and their rows:

* ``bearing`` -- Browne eq 4 as printed (asin), eq 8 (far-field approximation),
  production eq 4 (:func:`sonar_ring.localise.bearing`, atan2 and Heron) and
  the bearing of the production virtual image, judged on the bearing sweep.
* ``plane`` -- the reflection point X seen by R1: Browne's trigonometric chain
  (eqs 9-18) against :func:`sonar_ring.localise.plane`.
* ``corner`` -- the corner point: Browne eq 19 against :func:`sonar_ring.localise.corner`.
* ``edge`` -- the edge point: Browne's Appendix A against :func:`sonar_ring.localise.edge`.
* ``vertical`` -- how the 3-D path is made horizontal before localising with
  the production model of the echo's true class: not at all, Browne eq 26
  (``t - (t - (R + 2 d))``, his correction), or :func:`sonar_ring.localise.horizontal_path`.
* ``range-only`` -- a conventional ranger (:func:`sonar_ring.localise.on_axis`, the
  echo on the pair's axis, what ``sensor_msgs/Range`` and a costmap do) against
  the production corner model for every echo (no class known, Browne s7) and
  the production model of the true class.

The per-point least-squares baselines live in :mod:`sonar_ring.benchmark.least_squares`.
Positions are in the ring's sensor frame (m); Browne's formulas work in a pair
frame and are rotated into it (the rotation is timed with them).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from sonar_ring import localise as loc
from sonar_ring.benchmark.scenes import BearingSweep, PairRows
from sonar_ring.reference import browne
from sonar_ring.simulate import CORNER, EDGE, PLANE

PAPER, PRODUCTION, BASELINE = "paper", "production", "baseline"


@dataclass(frozen=True)
class Batch:
    """N ring echoes as the methods take them.

    Attributes
    ----------
    rows : PairRows
        Geometry and truth.
    paths : ndarray, shape (N, 2)
        Measured 3-D path lengths, m.
    horizontal : ndarray, shape (N, 2)
        Their exact horizontal parts ``sqrt(d^2 - dz^2)``, m (what the 2-D
        solvers of every family but ``vertical`` are given).
    cos_yaw, sin_yaw : ndarray, shape (N,)
        The pairs' facing, for Browne's pair frame.
    """

    rows: PairRows
    paths: np.ndarray
    horizontal: np.ndarray
    cos_yaw: np.ndarray
    sin_yaw: np.ndarray

    @classmethod
    def of(cls, rows: PairRows, paths: np.ndarray) -> Batch:
        """A batch from the rows and their measured 3-D paths (N, 2), m."""
        horizontal = loc.horizontal_path(paths, rows.dz).value
        return cls(rows, paths, horizontal, np.cos(rows.yaw), np.sin(rows.yaw))

    def take(self, index) -> Batch:
        """The echoes picked by a boolean mask or an index array (repeats allowed)."""
        return Batch(self.rows.select(index), self.paths[index], self.horizontal[index], self.cos_yaw[index],
                     self.sin_yaw[index])

    def __len__(self) -> int:
        return len(self.rows)

    @property
    def d1(self) -> np.ndarray:
        """Horizontal path to R1, (N,), m."""
        return self.horizontal[:, 0]

    @property
    def d2(self) -> np.ndarray:
        """Horizontal path to R2, (N,), m."""
        return self.horizontal[:, 1]

    def browne_constants(self) -> tuple[float, float]:
        """Browne's pair separation D and ring radius R, m (one value for the whole ring)."""
        separation, radius = self.rows.separation, self.rows.radius
        if np.ptp(separation) > 1e-12 or np.ptp(radius) > 1e-12:
            raise ValueError("Browne's formulas need one separation and one radius for all pairs")
        return float(separation[0]), float(radius[0])

    def from_pair_frame(self, point: np.ndarray) -> np.ndarray:
        """Points (N, 2) in Browne's pair frame (emitter at the origin, x along the pair) to the sensor frame."""
        x, y = point[:, 0], point[:, 1]
        return self.rows.tx + np.stack([self.cos_yaw * x - self.sin_yaw * y, self.sin_yaw * x + self.cos_yaw * y],
                                       axis=-1)


@dataclass(frozen=True)
class Method:
    """One row of the benchmark.

    Attributes
    ----------
    name : str
        What the report calls it.
    role : str
        :data:`PAPER`, :data:`PRODUCTION` or :data:`BASELINE`.
    solve : callable
        ``solve(inputs) -> (estimate, valid)``: positions (N, 2) in m or bearings
        (N,) in rad, and (N,) bool.
    timed : callable or None
        What "time per landmark" measures, ``timed(inputs)`` (``solve`` itself,
        or for ``vertical`` the correction alone); None where nothing is
        computed (no correction) or no single call does it (an ideal classifier).
    """

    name: str
    role: str
    solve: Callable
    timed: Callable | None


@dataclass(frozen=True)
class Family:
    """Methods judged on the same echoes against the same truth.

    Attributes
    ----------
    name : str
    unit : str
        ``"m"`` (positions) or ``"rad"`` (bearings).
    methods : tuple of Method
    classes : tuple of int
        Truth classes of the ring echoes it is judged on (empty: the bearing sweep).
    """

    name: str
    unit: str
    methods: tuple
    classes: tuple = ()

    def select(self, batch: Batch) -> Batch:
        """The echoes of this family's classes."""
        return batch.take(np.isin(batch.rows.truth_class, self.classes))


def truth_of(rows: PairRows) -> np.ndarray:
    """The point each echo is judged against, (N, 2), m: R1's reflection point (X) for planes, else the vertex."""
    return np.where((rows.truth_class == PLANE)[:, None], rows.truth_reflection, rows.truth_position)


def _geometry(batch: Batch):
    return batch.rows.tx, batch.rows.rx1, batch.rows.rx2


def production_point(model: str, batch: Batch, horizontal: np.ndarray | None = None):
    """Production estimate of ``model`` (plane: R1's reflection point), (N, 2) m, and valid (N,)."""
    paths = batch.horizontal if horizontal is None else horizontal
    estimate = loc.MODELS[model](*_geometry(batch), paths[:, 0], paths[:, 1])
    point = estimate.reflection_points[:, 0] if model == "plane" else estimate.position
    return point, estimate.valid


def true_class_point(batch: Batch, horizontal: np.ndarray | None = None):
    """Each echo localised with the production model of its true class (an ideal classifier)."""
    point = np.full((len(batch), 2), np.nan)
    valid = np.zeros(len(batch), dtype=bool)
    for model, code in (("plane", PLANE), ("corner", CORNER), ("edge", EDGE)):
        mine = batch.rows.truth_class == code
        if mine.any():
            part = batch.take(mine)
            point[mine], valid[mine] = production_point(model, part, None if horizontal is None
                                                        else horizontal[mine])
    return point, valid


def _browne_point(formula):
    def solve(batch: Batch):
        separation, radius = batch.browne_constants()
        point = batch.from_pair_frame(formula(batch.d1, batch.d2, separation, radius))
        return point, np.all(np.isfinite(point), axis=-1)

    return solve


def _production(model):
    return lambda batch: production_point(model, batch)


# --------------------------------------------------------------------------- vertical

def _eq26_horizontal(batch: Batch) -> np.ndarray:
    """Browne s6: subtract ``t - (R + 2 d)`` from each path, d from eq 26 with that receiver's height."""
    _, radius = batch.browne_constants()
    return radius + 2.0 * browne.vertical_eq26(batch.paths, batch.rows.dz, radius)


def _exact_horizontal(batch: Batch) -> np.ndarray:
    return loc.horizontal_path(batch.paths, batch.rows.dz).value


def _corrected(correction):
    return lambda batch: true_class_point(batch, correction(batch))


# --------------------------------------------------------------------------- bearing

def _bearing_of_image(sweep: BearingSweep, d1, d2):
    image = loc.virtual_image(sweep.tx, sweep.rx1, sweep.rx2, d1, d2)
    towards = image.position - sweep.rx1
    return np.arctan2(towards[:, 1], towards[:, 0]), image.valid


def _bearing_paper(formula):
    def solve(inputs):
        sweep, d1, d2 = inputs
        value = formula(d1, d2, sweep.separation)
        return value, np.isfinite(value)

    return solve


def _bearing_production(exact):
    def solve(inputs):
        sweep, d1, d2 = inputs
        result = loc.bearing(d1, d2, sweep.separation, exact=exact)
        return result.value, result.valid

    return solve


def _on_axis(batch: Batch):
    estimate = loc.on_axis(*_geometry(batch), batch.d1, batch.d2)
    return estimate.position, estimate.valid


def _timed(name: str, role: str, solve: Callable) -> Method:
    """A method whose time per landmark is that of its whole ``solve``."""
    return Method(name, role, solve, solve)


BEARING = Family("bearing", "rad", (
    _timed("Browne eq 4 as printed (asin)", PAPER, _bearing_paper(browne.bearing_eq4)),
    _timed("Browne eq 8 (far-field approximation)", PAPER, _bearing_paper(browne.bearing_eq8)),
    _timed("eq 4, production (`localise.bearing`: atan2, Heron)", PRODUCTION, _bearing_production(True)),
    _timed("virtual image closed form (`localise.virtual_image`)", PRODUCTION,
           lambda inputs: _bearing_of_image(*inputs)),
))

PLANE_FAMILY = Family("plane", "m", (
    _timed("Browne eqs 9-18 (trigonometric chain)", PAPER, _browne_point(browne.plane_point)),
    _timed("production `localise.plane` (virtual image)", PRODUCTION, _production("plane")),
), (PLANE,))

CORNER_FAMILY = Family("corner", "m", (
    _timed("Browne eq 19 (trigonometric chain)", PAPER, _browne_point(browne.corner_point)),
    _timed("production `localise.corner` (virtual image)", PRODUCTION, _production("corner")),
), (CORNER,))

EDGE_FAMILY = Family("edge", "m", (
    _timed("Browne Appendix A (closed form)", PAPER, _browne_point(browne.edge_point)),
    _timed("production `localise.edge` (quadratic)", PRODUCTION, _production("edge")),
), (EDGE,))

VERTICAL = Family("vertical", "m", (
    Method("none (3-D path taken as horizontal)", BASELINE, _corrected(lambda batch: batch.paths), None),
    Method("Browne eq 26 (R + 2d)", PAPER, _corrected(_eq26_horizontal), _eq26_horizontal),
    Method("exact `sqrt(d^2 - dz^2)` (`localise.horizontal_path`)", PRODUCTION, _corrected(_exact_horizontal),
           _exact_horizontal),
), (PLANE, CORNER, EDGE))

RANGE_ONLY = Family("range-only", "m", (
    _timed("conventional ranger: echo on the pair's axis (`localise.on_axis`)", BASELINE, _on_axis),
    _timed("production corner model for every echo (unclassified, Browne s7)", PRODUCTION, _production("corner")),
    Method("production model of the true class (ideal classifier)", PRODUCTION, true_class_point, None),
), (PLANE, CORNER, EDGE))

RING_FAMILIES = (PLANE_FAMILY, CORNER_FAMILY, EDGE_FAMILY, VERTICAL, RANGE_ONLY)
"""Families judged on the ring's echoes in the standard scenes."""

