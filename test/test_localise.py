"""Localisation core (sonar_ring.localise): round trips on Browne's grid, every model and the API."""

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal
from scipy.optimize import minimize_scalar

from sonar_ring import localise as loc
from sonar_ring.geometry import load_layout
from sonar_ring.reference import barshan_kuc

LD = np.longdouble  # ground truth is formed in extended precision, then rounded to the float64 inputs
C = 343.2
SIGMA_TOF = 1e-6


def norm(v):
    return np.sqrt(np.sum(np.square(v), axis=-1))


def browne_pair(group=0):
    ring = load_layout("browne_ring")
    rx = ring.group_receivers()[group, :, :2]
    return ring.transmitters[0, :2], rx[0], rx[1]


def browne_grid(stride_x, stride_y):
    """Browne's test grid (section 5) in the sensor frame of pair 0, subsampled.

    1 mm steps from 0.01 to 5.7 m in front of the pair and +-1 m to its sides;
    the strides keep the first and last rows and columns.
    """
    ahead = np.unique(np.r_[np.arange(10, 5701, stride_x), 5700]) / 1000.0
    side = np.unique(np.r_[np.arange(-1000, 1001, stride_y), 1000]) / 1000.0
    x, y = np.meshgrid(0.31 + ahead, side, indexing="ij")
    return np.stack([x, y], axis=-1).reshape(-1, 2)


def corner_paths(tx, rx1, rx2, point):
    image = 2 * point.astype(LD) - tx.astype(LD)
    return (norm(image - rx1.astype(LD)).astype(float), norm(image - rx2.astype(LD)).astype(float))


def edge_paths(tx, rx1, rx2, point):
    p = point.astype(LD)
    k = norm(p - tx.astype(LD))
    return (k + norm(p - rx1.astype(LD))).astype(float), (k + norm(p - rx2.astype(LD))).astype(float)


def true_reflection_point(tx, receiver, foot):
    """Specular point on the plane with foot point ``foot`` seen by ``receiver``, extended precision."""
    t, r, g = tx.astype(LD), receiver.astype(LD), foot.astype(LD)
    normal = (g - t) / norm(g - t)[..., None]
    image = 2 * g - t
    depth = np.sum((g - r) * normal, axis=-1)
    return (r + (depth / np.sum((image - r) * normal, axis=-1))[..., None] * (image - r)).astype(float)


# --------------------------------------------------------------------------- round trips on Browne's grid

GRID = browne_grid(37, 23)


def test_corner_round_trip_on_browne_grid():
    tx, rx1, rx2 = browne_pair()
    d1, d2 = corner_paths(tx, rx1, rx2, GRID)
    result = loc.corner(tx, rx1, rx2, d1, d2)
    assert result.valid.all()
    assert np.max(norm(result.position - GRID)) < 1e-11


def test_plane_round_trip_on_browne_grid():
    tx, rx1, rx2 = browne_pair()
    d1, d2 = corner_paths(tx, rx1, rx2, GRID)  # a plane with foot point G has the same virtual image
    result = loc.plane(tx, rx1, rx2, d1, d2)
    assert result.valid.all()
    assert np.max(norm(result.position - GRID)) < 1e-11
    normal = (GRID - tx) / norm(GRID - tx)[:, None]
    assert np.max(norm(result.normal - normal)) < 1e-13
    for n, receiver in enumerate((rx1, rx2)):
        truth = true_reflection_point(tx, receiver, GRID)
        assert np.max(norm(result.reflection_points[:, n] - truth)) < 1e-11
        # the reflection point lies on the plane
        assert np.max(np.abs(np.sum((result.reflection_points[:, n] - GRID) * normal, axis=-1))) < 1e-11


def test_edge_round_trip_on_browne_grid():
    tx, rx1, rx2 = browne_pair()
    d1, d2 = edge_paths(tx, rx1, rx2, GRID)
    result = loc.edge(tx, rx1, rx2, d1, d2)
    assert result.valid.all()
    assert np.max(norm(result.position - GRID)) < 1e-11


@pytest.mark.parametrize("group", [5, 17, 30])
def test_every_ring_pair_in_the_sensor_frame(group):
    tx, rx1, rx2 = browne_pair(group)
    yaw = np.radians(7.5 * group)
    rotation = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    points = GRID[::40] @ rotation.T
    for model, paths in (("corner", corner_paths), ("plane", corner_paths), ("edge", edge_paths)):
        result = loc.MODELS[model](tx, rx1, rx2, *paths(tx, rx1, rx2, points))
        assert result.valid.all(), model
        assert np.max(norm(result.position - points)) < 1e-11, model


def test_barshan_kuc_pair_both_transmitters():
    """Transducers a and b both fire: T = R1 for a, T = R2 for b (paths d = 2 R_xy)."""
    pair = load_layout("barshan_kuc_pair")
    a, b = pair.group_receivers()[0, :, :2]
    sep = pair.group_separation()[0]
    R, theta = np.meshgrid(np.linspace(0.2, 1.6, 15), np.radians(np.linspace(-10, 10, 21)), indexing="ij")
    direction = np.stack([np.cos(theta), np.sin(theta)], axis=-1)
    # plane at perpendicular distance R with inward normal at angle theta (Barshan & Kuc Fig. 7)
    r_aa, r_bb = R - sep / 2 * np.sin(theta), R + sep / 2 * np.sin(theta)
    r_ab = np.sqrt(R**2 + sep**2 * np.cos(theta) ** 2 / 4)
    for tx, d1, d2 in ((a, 2 * r_aa, 2 * r_ab), (b, 2 * r_ab, 2 * r_bb)):
        result = loc.plane(tx, a, b, d1, d2)
        assert result.valid.all()
        assert_allclose(np.arctan2(result.normal[..., 1], result.normal[..., 0]), theta, atol=1e-13)
        assert_allclose(np.sum(result.position * direction, axis=-1), R, atol=1e-14)
    # corner at range R and inclination theta: exact eqs 18-20
    r_aa, r_bb, r_ab = barshan_kuc.corner_ranges(R, theta, sep)
    apex = R[..., None] * direction
    for tx, d1, d2 in ((a, 2 * r_aa, 2 * r_ab), (b, 2 * r_ab, 2 * r_bb)):
        result = loc.corner(tx, a, b, d1, d2)
        assert result.valid.all()
        assert np.max(norm(result.position - apex)) < 1e-14


def test_kreczmer_triad_transmitter_between_receivers():
    """The triad's emitter lies on the receivers' line, between them (collinear in 2-D)."""
    triad = load_layout("kreczmer_triad")
    tx = triad.transmitters[0, :2]
    rx1, rx2 = triad.group_receivers()[0, [0, 2], :2]
    rng = np.random.default_rng(7)
    points = np.column_stack([rng.uniform(0.05, 3.0, 2000), rng.uniform(-1.5, 1.5, 2000)])
    for model, paths in (("corner", corner_paths), ("plane", corner_paths), ("edge", edge_paths)):
        result = loc.MODELS[model](tx, rx1, rx2, *paths(tx, rx1, rx2, points))
        assert result.valid.all(), model
        assert np.max(norm(result.position - points)) < 1e-11, model


def test_leading_shapes_broadcast():
    tx, rx1, rx2 = browne_pair()
    points = GRID[:24].reshape(2, 3, 4, 2)
    d1, d2 = corner_paths(tx, rx1, rx2, points)
    result = loc.plane(tx, rx1, rx2, d1, d2)
    assert result.position.shape == (2, 3, 4, 2)
    assert result.reflection_points.shape == (2, 3, 4, 2, 2)
    assert result.valid.shape == result.reason.shape == (2, 3, 4)
    assert result.reason.dtype == np.int8
    # per-entry geometry broadcasts too: two pairs, one echo each
    txs = np.stack([tx, tx])
    both = loc.corner(txs, np.stack([rx1, rx1]), np.stack([rx2, rx2]), d1[0, 0, :2], d2[0, 0, :2])
    assert_allclose(both.position, points[0, 0, :2], atol=1e-12)
    scalar = loc.edge(tx, rx1, rx2, *edge_paths(tx, rx1, rx2, GRID[5]))
    assert scalar.position.shape == (2,) and scalar.valid.shape == ()
    assert_allclose(scalar.position, GRID[5], atol=1e-12)


def test_a_shared_value_gives_what_one_per_entry_gives():
    """One geometry (or one path) for every entry is read in place: bit-identical to it copied to each entry."""
    tx, rx1, rx2 = browne_pair()
    d1, d2 = edge_paths(tx, rx1, rx2, GRID[:300])
    d1[:3] = [np.nan, -1.0, np.inf]
    every = [np.tile(point, (300, 1)) for point in (tx, rx1, rx2)]
    for name in ("virtual_image", "plane", "corner", "edge", "on_axis"):
        function = getattr(loc, name)
        expected = function(*every, d1, d2)
        for shared in ((tx, rx1, rx2, d1, d2), (tx, *every[1:], d1, d2), (*every, d1[7], d2)):
            result = function(*shared)
            per_entry = function(*(np.broadcast_to(a, e.shape) for a, e in zip(shared, (*every, d1, d2),
                                                                                  strict=True)))
            assert_array_equal(result.position, per_entry.position)
            assert_array_equal(result.reason, per_entry.reason)
        assert_array_equal(function(tx, rx1, rx2, d1, d2).position, expected.position)
    assert rx1.flags.writeable and d1.flags.writeable  # the caller's arrays are left as they were


def test_hypotheses_equal_the_models_one_by_one():
    """One validation and one shared virtual image give bit-identical results, invalid entries included."""
    tx, rx1, rx2 = browne_pair()
    d1, d2 = corner_paths(tx, rx1, rx2, GRID[:200])
    d1 = d1.copy()
    d1[:5] = [np.nan, -1.0, d2[2] + 0.05, 0.01, np.inf]
    together = loc.hypotheses(tx, rx1, rx2, d1, d2)
    assert list(together) == ["plane", "corner", "edge"]
    for name, function in loc.MODELS.items():
        alone = function(tx, rx1, rx2, d1, d2)
        assert_array_equal(together[name].position, alone.position)
        assert_array_equal(together[name].reason, alone.reason)
        assert_array_equal(together[name].valid, alone.valid)
    assert_array_equal(together["plane"].reflection_points, loc.plane(tx, rx1, rx2, d1, d2).reflection_points)
    assert list(loc.hypotheses(tx, rx1, rx2, d1, d2, ["edge"])) == ["edge"]


def test_invalid_entries_are_nan_and_valid_entries_are_not():
    tx, rx1, rx2 = browne_pair()
    d1, d2 = corner_paths(tx, rx1, rx2, GRID[:4])
    d1 = d1.copy()
    d1[1] = np.nan
    d1[2] = d2[2] + 0.05  # |d2 - d1| > D
    result = loc.plane(tx, rx1, rx2, d1, d2)
    assert_array_equal(result.valid, [True, False, False, True])
    assert_array_equal(result.reason, [loc.OK, loc.NOT_FINITE, loc.NO_INTERSECTION, loc.OK])
    assert np.isnan(result.position[~result.valid]).all() and np.isnan(result.normal[~result.valid]).all()
    assert np.isfinite(result.position[result.valid]).all()
    assert set(loc.REASONS) == set(range(9))


# --------------------------------------------------------------------------- bearing, vertical, on-axis

def test_bearing_exact_matches_the_geometry():
    rx1, rx2 = np.array([0.0, 0.02]), np.array([0.0, -0.02])
    phi = np.radians(np.linspace(-89, 89, 179))
    distance = np.array([0.05, 0.5, 1.0, 5.7, 10.0])[:, None]
    image = rx1 + distance[..., None] * np.stack([np.cos(phi), np.sin(phi)], axis=-1)
    d1, d2 = norm(image - rx1), norm(image - rx2)
    result = loc.bearing(d1, d2, 0.04)
    assert result.valid.all()
    assert_allclose(result.value, np.broadcast_to(phi, d1.shape), atol=1e-13)
    # CCW positive: eq 3 says sin(phi_1) has the sign of d2^2 - d1^2 - D^2 (far away: the echo is nearer R1)
    assert_array_equal(np.sign(result.value), np.sign(d2**2 - d1**2 - 0.04**2))


def test_far_field_bearing_error_quoted_by_browne():
    """Eq 8 vs eq 4 with D = 40 mm: about 2.3, 1.2 and 0.39 deg at 0.5, 1 and 3 m."""
    d1 = np.array([0.5, 1.0, 3.0])
    d2 = np.sqrt(d1**2 + 0.04**2)  # echo straight ahead of R1
    exact = loc.bearing(d1, d2, 0.04)
    approximate = loc.bearing(d1, d2, 0.04, exact=False)
    assert_allclose(exact.value, 0.0, atol=1e-13)
    # the dropped term of eq 5 is D / (2 d1); Browne quotes it rounded
    assert_allclose(approximate.value - exact.value, np.arcsin(0.04 / (2 * d1)), rtol=2e-3)
    assert_allclose(np.degrees(approximate.value - exact.value), [2.3, 1.2, 0.39], rtol=0.05)


def test_horizontal_path_unfolds_vertical_planes_and_poles():
    """Transmitter and receiver at different heights: the 3-D path's horizontal part is sqrt(d^2 - dz^2)."""
    tx = np.array([0.0, 0.0, 0.08])
    rx = np.array([0.31, 0.02, -0.045])
    dz = tx[2] - rx[2]
    # a vertical wall x = 1.5: mirror the transmitter in it
    mirrored = tx * [-1, 1, 1] + [3.0, 0, 0]
    path_3d = norm(mirrored - rx)
    path_2d = norm(mirrored[:2] - rx[:2])
    assert_allclose(loc.horizontal_path(path_3d, dz).value, path_2d, rtol=1e-15)
    # a vertical pole at (1.2, 0.4): Fermat's shortest path over the reflection height z
    pole = np.array([1.2, 0.4])
    a, b = norm(pole - tx[:2]), norm(pole - rx[:2])
    shortest = minimize_scalar(lambda z: np.hypot(a, z - tx[2]) + np.hypot(b, z - rx[2]),
                               bounds=(-1, 1), method="bounded", options={"xatol": 1e-12}).fun
    assert_allclose(loc.horizontal_path(shortest, dz).value, a + b, rtol=1e-12)
    assert_allclose(loc.horizontal_path(shortest, -dz).value, a + b, rtol=1e-12)


def test_on_axis_conventional_ranger():
    # a transducer that transmits and receives at the pair's mid-point: r = d / 2
    result = loc.on_axis([0.0, 0.0], [0.0, 0.02], [0.0, -0.02], [2.0, 3.0], [2.0, 3.2])
    assert_allclose(result.position, [[1.0, 0.0], [1.55, 0.0]], atol=1e-15)
    # Browne's emitter behind the pair: the on-axis echo round-trips exactly
    tx, rx1, rx2 = browne_pair()
    target = np.array([[0.31 + 1.7, 0.0]])
    mid = 0.5 * (rx1 + rx2)
    d = norm(target - tx) + norm(target - mid)
    assert_allclose(loc.on_axis(tx, rx1, rx2, d, d).position, target, atol=1e-14)
    # bearing is ignored: an off-axis corner is put on the axis at about its range
    corner = np.array([[1.5, 0.4]])
    off = loc.on_axis(tx, rx1, rx2, *corner_paths(tx, rx1, rx2, corner))
    assert off.valid.all() and off.position[0, 1] == 0.0
    assert_allclose(norm(off.position - mid), norm(corner - mid), rtol=0.05)


# --------------------------------------------------------------------------- errors

def test_error_handling():
    tx, rx1, rx2 = browne_pair()
    for function in (loc.virtual_image, loc.plane, loc.corner, loc.edge, loc.on_axis):
        with pytest.raises(ValueError, match=r"'tx' must be \(\.\.\., 2\)"):
            function([0.0, 0.0, 0.0], rx1, rx2, 1.0, 1.0)
        with pytest.raises(ValueError, match="'d1' must be real numbers"):
            function(tx, rx1, rx2, "1.0", 1.0)
        with pytest.raises(ValueError, match="do not broadcast"):
            function(tx, rx1, rx2, np.ones(3), np.ones(4))
        # bad data values never raise: they are flagged
        result = function(tx, rx1, rx2, [np.nan, -1.0, 0.0, np.inf, 0.2], [1.0, 1.0, 1.0, 1.0, 0.2])
        assert_array_equal(result.reason, [loc.NOT_FINITE, loc.NEGATIVE, loc.NEGATIVE, loc.NOT_FINITE, loc.TOO_SHORT])
        assert not result.valid.any()
    with pytest.raises(ValueError, match=r"unknown models \['wall'\]"):
        loc.hypotheses(tx, rx1, rx2, 1.0, 1.0, ["plane", "wall"])
    with pytest.raises(ValueError, match="hypotheses: 'd2' must be real numbers"):
        loc.hypotheses(tx, rx1, rx2, 1.0, "1.0")
    with pytest.raises(ValueError, match="'rx2' must be real numbers"):
        loc.plane(tx, rx1, np.array([1j, 0]), 1.0, 1.0)
    with pytest.raises(ValueError, match="'separation' must be real"):
        loc.bearing(1.0, 1.0, None)
    with pytest.raises(ValueError, match="'dz' must be real"):
        loc.horizontal_path(1.0, "up")
    # coincident receivers are data-dependent geometry: flagged, not raised
    assert loc.corner(tx, rx1, rx1, 1.0, 1.0).reason == loc.DEGENERATE
    assert loc.bearing(1.0, 1.0, 0.0).reason == loc.DEGENERATE


def test_reflector_paths_against_a_50_digit_reference():
    import mpmath

    mpmath.mp.dps = 50
    rng = np.random.default_rng(12)
    tx, rx = rng.normal(0.0, 0.1, (40, 2)), rng.normal(0.0, 0.1, (40, 3, 2))
    position, is_edge = rng.uniform(-4.0, 4.0, (40, 2)), rng.random(40) < 0.5
    paths = loc.reflector_paths(tx, rx, position, is_edge)
    assert paths.shape == (40, 3)
    for n in range(40):
        t, p = ([mpmath.mpf(float(v)) for v in vector] for vector in (tx[n], position[n]))
        for k in range(3):
            r = [mpmath.mpf(float(v)) for v in rx[n, k]]
            if is_edge[n]:  # the edge re-radiates from p
                reference = mpmath.hypot(p[0] - t[0], p[1] - t[1]) + mpmath.hypot(p[0] - r[0], p[1] - r[1])
            else:  # a plane, a corner or an undecided point: the virtual image 2p - T
                reference = mpmath.hypot(2 * p[0] - t[0] - r[0], 2 * p[1] - t[1] - r[1])
            assert abs(paths[n, k] - float(reference)) <= 1e-15 * float(reference)
