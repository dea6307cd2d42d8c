"""Hard cases of the localisation core against 50-digit references (mpmath).

Each reference solves the same equations for the *same float64 inputs* in
50-digit arithmetic, so a difference is the production path's own error.  The
contract: every result is either accurate or flagged invalid -- never a silent
NaN, never the wrong root.
"""

import mpmath as mp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal

from sonar_ring import localise as loc
from sonar_ring import uncertainty
from sonar_ring.reference import browne

mp.mp.dps = 50
EPS = np.finfo(float).eps
SEPARATION = 0.04
BROWNE = (np.array([0.0, 0.0]), np.array([0.31, 0.02]), np.array([0.31, -0.02]))  # ring centre, R1, R2
CENTRED = (np.array([0.0, 0.0]), np.array([0.0, 0.02]), np.array([0.0, -0.02]))  # transmitter between receivers


def norm(v):
    return np.sqrt(np.sum(np.square(v), axis=-1))


# --------------------------------------------------------------------------- 50-digit references

def mp_vec(p):
    return mp.matrix([mp.mpf(float(p[0])), mp.mpf(float(p[1]))])


def mp_frame(rx1, rx2):
    r1, r2 = mp_vec(rx1), mp_vec(rx2)
    sep = mp.norm(r2 - r1)
    u = (r2 - r1) / sep
    return r1, r2, sep, u, mp.matrix([-u[1], u[0]])


def mp_image(tx, rx1, rx2, d1, d2):
    """T' at d1 from R1 and d2 from R2 in front of the receivers, by the textbook formula in 50 digits."""
    r1, _, sep, u, n = mp_frame(rx1, rx2)
    d1, d2 = mp.mpf(float(d1)), mp.mpf(float(d2))
    along = (d1**2 - d2**2 + sep**2) / (2 * sep)
    return r1 + along * u + mp.sqrt(d1**2 - along**2) * n


def mp_bearing(d1, d2, sep):
    d1, d2, sep = mp.mpf(float(d1)), mp.mpf(float(d2)), mp.mpf(float(sep))
    return mp.asin((d2**2 - d1**2 - sep**2) / (2 * d1 * sep))


def mp_edge(tx, rx1, rx2, d1, d2, start):
    """Newton on |P-T| + |P-R_n| = d_n from ``start`` (the known true edge), in 50 digits."""
    t, r1, r2 = mp_vec(tx), mp_vec(rx1), mp_vec(rx2)
    d1, d2 = mp.mpf(float(d1)), mp.mpf(float(d2))

    def residual(x, y):
        p = mp.matrix([x, y])
        return [mp.norm(p - t) + mp.norm(p - r1) - d1, mp.norm(p - t) + mp.norm(p - r2) - d2]

    solution = mp.findroot(residual, (mp.mpf(float(start[0])), mp.mpf(float(start[1]))), verify=False,
                           maxsteps=200)
    assert max(abs(r) for r in residual(solution[0], solution[1])) < mp.mpf(10) ** -40
    return solution


def as_float(vector):
    return np.array([float(vector[0]), float(vector[1])])


def corner_inputs(tx, rx1, rx2, point):
    """Float64 paths of a corner at ``point`` (rounded from 50 digits)."""
    image = 2 * mp_vec(point) - mp_vec(tx)
    return float(mp.norm(image - mp_vec(rx1))), float(mp.norm(image - mp_vec(rx2)))


def edge_inputs(tx, rx1, rx2, point):
    p = mp_vec(point)
    k = mp.norm(p - mp_vec(tx))
    return float(k + mp.norm(p - mp_vec(rx1))), float(k + mp.norm(p - mp_vec(rx2)))


def tolerance(estimate, tx, rx1, rx2, d1, d2, ulps=32):
    """``ulps`` units of roundoff in the paths, propagated by the problem's own condition number."""
    jacobian = uncertainty.position_jacobian(estimate, tx, rx1, rx2)
    gain = np.linalg.norm(jacobian, 2) if np.all(np.isfinite(jacobian)) else np.inf
    return ulps * EPS * (max(d1, d2) * max(1.0, gain) + norm(estimate.position))


# --------------------------------------------------------------------------- d1 ~ d2 at long range

DELTAS = [0.0, EPS * 11.7, 10 * EPS * 11.7, 1e-12, 1e-9, 1e-6, 1e-3]


@pytest.mark.parametrize("delta", DELTAS + [-d for d in DELTAS[1:]])
def test_nearly_equal_paths_at_long_range(delta):
    """d1 ~ d2 ~ 11.7 m (a reflector 5.7 m ahead): no cancellation in the bearing or the image."""
    tx, rx1, rx2 = BROWNE
    d1 = 11.7
    d2 = d1 + delta
    image = loc.virtual_image(tx, rx1, rx2, d1, d2)
    truth = as_float(mp_image(tx, rx1, rx2, d1, d2))
    assert image.valid
    assert np.max(np.abs(image.position - truth)) <= 4 * EPS * 11.7
    exact_bearing = mp_bearing(d1, d2, SEPARATION)
    result = loc.bearing(d1, d2, SEPARATION)
    assert abs(result.value - float(exact_bearing)) <= 4 * EPS * (abs(float(exact_bearing)) + 11.7 / SEPARATION * EPS)
    corner = loc.corner(tx, rx1, rx2, d1, d2)
    assert_allclose(corner.position, 0.5 * (tx + truth), atol=4 * EPS * 11.7)
    # Browne's eq 4 squares the paths first: its error is the rounding of d^2 ~ 137 over 2 d1 D
    assert abs(browne.bearing_eq4(d1, d2, SEPARATION) - float(exact_bearing)) < 1e-12


def test_eq4_loses_digits_where_the_production_bearing_does_not():
    d1 = 11.7
    d2 = d1 + np.array([1e-9, 3e-8, 1e-6, 7e-5])
    exact = np.array([float(mp_bearing(d1, b, SEPARATION)) for b in d2])
    production = np.abs(loc.bearing(d1, d2, SEPARATION).value - exact)
    paper = np.abs(browne.bearing_eq4(d1, d2, SEPARATION) - exact)
    assert np.all(production <= 4 * EPS * np.abs(exact) + 1e-17)
    assert np.max(paper) > 100 * np.max(production)


# --------------------------------------------------------------------------- bearings near +-90 degrees

@pytest.mark.parametrize("digits", range(1, 15))
@pytest.mark.parametrize("side", [1, -1])
def test_near_tangent_circles(digits, side):
    """|d2 - d1| -> D: the virtual image approaches the receivers' line (bearing -> +-90 deg)."""
    tx, rx1, rx2 = CENTRED
    for d1 in (0.1, 1.0, 10.0):
        d2 = d1 + side * SEPARATION * (1 - 10.0**-digits)
        image = loc.virtual_image(tx, rx1, rx2, d1, d2)
        truth = mp_image(tx, rx1, rx2, d1, d2)
        assert image.valid
        # the height over the baseline keeps its relative accuracy however small it gets
        height = float(truth[0])
        assert abs(image.position[0] - height) <= 8 * EPS * height
        assert abs(image.position[1] - float(truth[1])) <= 4 * EPS * (d1 + d2)
        exact = mp_bearing(d1, d2, SEPARATION)
        assert abs(loc.bearing(d1, d2, SEPARATION).value - float(exact)) <= 8 * EPS
    # Browne's asin form is ill-conditioned here: it keeps only about half the digits
    assert abs(browne.bearing_eq4(1.0, 1.0 + side * SEPARATION * (1 - 1e-14), SEPARATION)
               - float(mp_bearing(1.0, 1.0 + side * SEPARATION * (1 - 1e-14), SEPARATION))) > 1e-9


@pytest.mark.parametrize("excess", [1e-15, 1e-12, 1e-6])
def test_just_outside_the_tangent_is_flagged(excess):
    tx, rx1, rx2 = CENTRED
    for sign in (1, -1):
        d2 = 1.0 + sign * SEPARATION * (1 + excess)
        for result in (loc.virtual_image(tx, rx1, rx2, 1.0, d2), loc.plane(tx, rx1, rx2, 1.0, d2),
                       loc.corner(tx, rx1, rx2, 1.0, d2), loc.edge(tx, rx1, rx2, 1.0, d2),
                       loc.bearing(1.0, d2, SEPARATION)):
            assert result.reason == loc.NO_INTERSECTION and not result.valid
    # circles that are too small to meet: d1 + d2 < D
    assert loc.virtual_image(tx, rx1, rx2, 0.015, 0.015 + 0.005).reason == loc.NO_INTERSECTION
    assert loc.bearing(0.015, 0.02, SEPARATION).reason == loc.NO_INTERSECTION


# --------------------------------------------------------------------------- ranges 0.01 m to 10 m

RANGES = np.geomspace(0.01, 10.0, 13)
ANGLES = np.radians([-80, -45, -10, 0, 3, 30, 60, 85])


@pytest.mark.parametrize("geometry", ["browne", "centred"])
@pytest.mark.parametrize("model", ["corner", "plane", "edge"])
def test_ranges_from_a_centimetre_to_ten_metres(geometry, model):
    tx, rx1, rx2 = BROWNE if geometry == "browne" else CENTRED
    mid = 0.5 * (rx1 + rx2)
    checked = 0
    for r in RANGES:
        for phi in ANGLES:
            point = mid + r * np.array([np.cos(phi), np.sin(phi)])
            paths = edge_inputs if model == "edge" else corner_inputs
            d1, d2 = paths(tx, rx1, rx2, point)
            result = loc.MODELS[model](tx, rx1, rx2, d1, d2)
            if model == "edge":
                truth = as_float(mp_edge(tx, rx1, rx2, d1, d2, point))
            else:
                truth = 0.5 * (tx + as_float(mp_image(tx, rx1, rx2, d1, d2)))
            image_ahead = np.dot(2 * point - tx - mid, [1.0, 0.0]) > 0
            if model != "edge" and (not image_ahead or min(d1 - norm(rx1 - tx), d2 - norm(rx2 - tx)) < 0):
                # the echo would arrive from behind, or the path is shorter than the direct one
                assert not result.valid or np.dot(result.position - mid, [1.0, 0.0]) > 0
                continue
            assert result.valid, (r, phi, result.reason)
            error = np.max(np.abs(result.position - truth))
            assert error <= tolerance(result, tx, rx1, rx2, d1, d2), (r, phi, error)
            assert np.max(np.abs(result.position - point)) <= tolerance(result, tx, rx1, rx2, d1, d2, ulps=64)
            checked += 1
    assert checked >= 60


# --------------------------------------------------------------------------- the solvable region's borders

def test_direct_path_border():
    """d_n just below / above the direct path |T - R_n|."""
    tx, rx1, rx2 = BROWNE
    direct = norm(rx1 - tx)
    d2 = direct + 0.03
    below = loc.corner(tx, rx1, rx2, direct * (1 - 1e-12), d2)
    assert below.reason == loc.TOO_SHORT and np.isnan(below.position).all()
    above = loc.plane(tx, rx1, rx2, direct * (1 + 1e-12), d2)
    assert above.valid
    image = as_float(mp_image(tx, rx1, rx2, direct * (1 + 1e-12), d2))
    assert_allclose(above.position, 0.5 * (tx + image), atol=tolerance(above, tx, rx1, rx2, direct, d2))
    assert loc.edge(tx, rx1, rx2, direct * (1 - 1e-12), d2).reason == loc.TOO_SHORT


@pytest.mark.parametrize("lateral", [0.0, 0.012, -0.019])
def test_edge_just_in_front_of_and_behind_the_pair(lateral):
    tx, rx1, rx2 = BROWNE
    for offset, expected in ((1e-6, loc.OK), (1e-9, loc.OK), (-1e-9, loc.BEHIND), (-1e-3, loc.BEHIND)):
        point = np.array([0.31 + offset, lateral])
        d1, d2 = edge_inputs(tx, rx1, rx2, point)
        result = loc.edge(tx, rx1, rx2, d1, d2)
        assert result.reason == expected, (offset, result.reason)
        if expected == loc.OK:
            truth = as_float(mp_edge(tx, rx1, rx2, d1, d2, point))
            assert np.max(np.abs(result.position - truth)) <= tolerance(result, tx, rx1, rx2, d1, d2)


@pytest.mark.parametrize("lateral", [0.03, 0.3, -1.0])
def test_edge_near_the_receivers_line_beside_the_pair(lateral):
    """Beside the pair on its line |d2 - d1| -> D: the ellipses touch, so the problem itself is ill-conditioned."""
    tx, rx1, rx2 = BROWNE
    for offset in (1e-3, 1e-6, 1e-9, -1e-9, -1e-6, -1e-3):
        point = np.array([0.31 + offset, lateral])
        d1, d2 = edge_inputs(tx, rx1, rx2, point)
        result = loc.edge(tx, rx1, rx2, d1, d2)
        if offset < 0 and result.valid:
            # the second intersection, just in front: it produces the same paths
            assert result.position[0] > 0.31
            assert_allclose(edge_inputs(tx, rx1, rx2, result.position), (d1, d2), rtol=1e-14)
        elif result.valid:
            truth = as_float(mp_edge(tx, rx1, rx2, d1, d2, point))
            assert np.max(np.abs(result.position - truth)) <= tolerance(result, tx, rx1, rx2, d1, d2)
        else:
            assert result.reason in (loc.NO_INTERSECTION, loc.BEHIND) and abs(offset) <= 1e-6


def test_corner_behind_the_receivers_is_flagged():
    tx, rx1, rx2 = BROWNE
    for offset, expected in ((1e-9, loc.OK), (-1e-9, loc.BEHIND)):
        d1, d2 = corner_inputs(tx, rx1, rx2, np.array([0.31 + offset, 0.6]))
        assert loc.corner(tx, rx1, rx2, d1, d2).reason == expected


# --------------------------------------------------------------------------- edge: vanishing leading coefficient

def test_edge_quadratic_with_vanishing_leading_coefficient():
    """The leading coefficient vanishes only as d_n -> |T - R_n| (an edge on the direct paths, at T).

    Browne's Appendix A denominator is the same coefficient: for d1 = d2 = R it
    is exactly zero and his closed form divides by it.  The production path
    flags such data (shorter than the direct path, or behind the receivers) and
    stays finite.
    """
    tx, rx1, rx2 = BROWNE
    ring_radius = 0.31
    with np.errstate(divide="ignore", invalid="ignore"):
        assert not np.all(np.isfinite(browne.edge_solutions(ring_radius, ring_radius, SEPARATION, ring_radius)))
    assert loc.edge(tx, rx1, rx2, ring_radius, ring_radius).reason == loc.TOO_SHORT
    # approaching the boundary from the valid side: the edge nears the transmitter, behind the pair
    direct = norm(rx1 - tx)
    for excess in (1e-3, 1e-6, 1e-9, 1e-12, 1e-15):
        result = loc.edge(tx, rx1, rx2, direct * (1 + excess), direct * (1 + excess))
        # two nearly coincident intersections behind the pair, or touching within rounding
        assert result.reason in (loc.BEHIND, loc.NO_INTERSECTION) and np.isnan(result.position).all()


@pytest.mark.parametrize("transmitter", [[0.6, -0.3], [1.0, -0.3], [0.01, 0.5], [0.3, 0.1]])
def test_edge_near_a_transmitter_in_front(transmitter):
    """A transmitter in front of the receivers, edges closing in on it: accurate, or flagged AMBIGUOUS.

    Near the transmitter both intersections of the two ellipses are in front of
    the receivers, so no rule can pick one: the production path says so.  An
    edge behind the receivers is answered with the one solution in front, which
    produces the same paths.
    """
    tx = np.array(transmitter)
    _, rx1, rx2 = CENTRED
    outcomes = set()
    for distance in (1e-1, 1e-2, 1e-3, 1e-4, 1e-6):
        for angle in (0.0, 1.0, 2.0, 3.0, 4.0, 5.0):
            point = tx + distance * np.array([np.cos(angle), np.sin(angle)])
            d1, d2 = edge_inputs(tx, rx1, rx2, point)
            result = loc.edge(tx, rx1, rx2, d1, d2)
            outcomes.add(int(result.reason))
            if not result.valid:
                assert result.reason == loc.AMBIGUOUS and np.isnan(result.position).all()
            elif point[0] > 0:
                truth = as_float(mp_edge(tx, rx1, rx2, d1, d2, point))
                assert np.max(np.abs(result.position - truth)) <= tolerance(result, tx, rx1, rx2, d1, d2)
            else:
                assert result.position[0] > 0
                assert_allclose(edge_inputs(tx, rx1, rx2, result.position), (d1, d2), rtol=1e-12)
    assert loc.OK in outcomes


# --------------------------------------------------------------------------- float32, bad values

def test_float32_inputs_are_computed_in_float64():
    tx, rx1, rx2 = BROWNE
    points = np.array([[1.2, 0.3], [4.0, -0.9], [0.35, 0.01]])
    for model, paths in (("corner", corner_inputs), ("plane", corner_inputs), ("edge", edge_inputs)):
        d = np.array([paths(tx, rx1, rx2, p) for p in points], dtype=np.float32)
        single = loc.MODELS[model](tx.astype(np.float32), rx1.astype(np.float32), rx2.astype(np.float32),
                                   d[:, 0], d[:, 1])
        double = loc.MODELS[model](tx.astype(np.float32).astype(float), rx1.astype(np.float32).astype(float),
                                   rx2.astype(np.float32).astype(float), d[:, 0].astype(float),
                                   d[:, 1].astype(float))
        assert single.position.dtype == np.float64
        assert_array_equal(single.position, double.position)
        # float32 rounding of the inputs (~6e-8 relative) is all that is lost
        assert np.max(norm(single.position - points)) < 1e-4


def test_non_finite_negative_and_mixed_inputs():
    tx, rx1, rx2 = BROWNE
    d1 = np.array([np.nan, np.inf, -np.inf, -1.0, 0.0, 2.0, 2.0, 2.0])
    d2 = np.array([2.0, 2.0, 2.0, 2.0, 2.0, np.nan, -2.0, 2.01])
    expected = [loc.NOT_FINITE] * 3 + [loc.NEGATIVE] * 2 + [loc.NOT_FINITE, loc.NEGATIVE, loc.OK]
    for function in (loc.virtual_image, loc.plane, loc.corner, loc.edge, loc.on_axis):
        result = function(tx, rx1, rx2, d1, d2)
        assert_array_equal(result.reason, expected)
        assert np.isnan(result.position[:-1]).all() and np.isfinite(result.position[-1]).all()
    assert_array_equal(loc.bearing(d1, d2, SEPARATION).reason, expected)
    bad_geometry = loc.edge(np.array([[np.nan, 0.0], [0.0, 0.0]]), rx1, [[0.31, -0.02], [0.31, np.inf]], 2.0, 2.0)
    assert_array_equal(bad_geometry.reason, [loc.NOT_FINITE, loc.NOT_FINITE])
    assert_array_equal(loc.horizontal_path([np.nan, -1.0, 0.0], 0.0).reason,
                       [loc.NOT_FINITE, loc.NEGATIVE, loc.NEGATIVE])


def test_path_below_the_height_difference():
    result = loc.horizontal_path([0.05, 0.08, 0.08 * (1 + 1e-15), 1.0], 0.08)
    assert_array_equal(result.reason, [loc.BELOW_HEIGHT, loc.OK, loc.OK, loc.OK])
    assert result.value[1] == 0.0 and np.isnan(result.value[0])
    # d ~ dz: the factored form keeps full relative accuracy, the textbook one does not
    d, dz = 0.08 * (1 + 2.0**-40), 0.08
    exact = float(mp.sqrt(mp.mpf(d) ** 2 - mp.mpf(dz) ** 2))
    assert abs(loc.horizontal_path(d, dz).value - exact) <= 2 * EPS * exact
    assert abs(np.sqrt(d**2 - dz**2) - exact) > 1e6 * EPS * exact
    assert abs(browne.vertical_eq26(d, dz, 0.0) * 2 - exact) > 1e6 * EPS * exact


@pytest.mark.parametrize("gap", [1e-1, 1e-2, 2.2e-3, 1e-4, 1e-5])
def test_an_edge_near_the_transmitter_reproduces_its_paths(gap):
    """An edge ``gap`` m from a transmitter 1 m beside a 125 mm pair, 1 cm ahead of it (found by hypothesis).

    Its distance k from the transmitter comes out of a difference of squared paths that cancels by
    about d / k; the Newton step restores the paths to a few ulps.
    """
    tx, rx1, rx2 = np.array([0.01 - gap, 1.0]), np.array([0.0, 0.0625]), np.array([0.0, -0.0625])
    point = np.array([0.01, 1.0])
    d1, d2 = edge_inputs(tx, rx1, rx2, point)
    result = loc.edge(tx, rx1, rx2, d1, d2)
    assert result.valid
    assert_allclose(edge_inputs(tx, rx1, rx2, result.position), (d1, d2), rtol=4 * EPS, atol=4 * EPS)


# --------------------------------------------------------------------------- random configurations

@settings(max_examples=300, deadline=None)
@given(tx=st.tuples(st.floats(-1.0, 0.2), st.floats(-1.0, 1.0)),
       yaw=st.floats(-np.pi, np.pi), separation=st.floats(0.005, 0.3),
       ahead=st.floats(0.01, 8.0), side=st.floats(-4.0, 4.0),
       model=st.sampled_from(["corner", "plane", "edge"]))
def test_random_configurations_are_accurate_or_flagged(tx, yaw, separation, ahead, side, model):
    """Any transmitter, any pair orientation: valid results reproduce the truth; others are flagged."""
    facing = np.array([np.cos(yaw), np.sin(yaw)])
    left = np.array([-facing[1], facing[0]])
    tx = np.array(tx) @ np.array([facing, left])  # transmitter coordinates given in the pair's frame
    rx1, rx2 = 0.5 * separation * left, -0.5 * separation * left
    point = ahead * facing + side * left
    paths = edge_inputs if model == "edge" else corner_inputs
    d1, d2 = paths(tx, rx1, rx2, point)
    result = loc.MODELS[model](tx, rx1, rx2, d1, d2)
    assert result.valid == (result.reason == loc.OK)
    if not result.valid:
        assert np.isnan(result.position).all()
        if result.reason == loc.DEGENERATE:
            assert model == "plane" and norm(point - tx) < 1e-12  # transmitter on the plane: no normal
            return
        assert result.reason in (loc.TOO_SHORT, loc.BEHIND, loc.AMBIGUOUS, loc.NO_INTERSECTION)
        if model != "edge":
            # only echoes from behind (image not ahead) or impossible paths are refused
            image_ahead = np.dot(2 * point - tx, facing) > 0
            assert not image_ahead or result.reason in (loc.TOO_SHORT, loc.BEHIND)
        return
    assert np.all(np.isfinite(result.position))
    if model == "edge" and norm(point - tx) < 1e-6:
        # An edge at the transmitter: both paths are direct ones (the TOO_SHORT border), the two ellipses
        # degenerate to segments that meet only there, and |P - T| is not differentiable -- the edge is
        # determined to about sqrt(eps) only.
        assert norm(result.position - point) < 1e-6
        return
    # backward stable: the answer reproduces the measured paths
    assert_allclose(paths(tx, rx1, rx2, result.position), (d1, d2), rtol=64 * EPS, atol=64 * EPS)
    if model == "edge":
        truth = point
    else:
        image_ahead = np.dot(2 * point - tx, facing) > 0
        truth = point if image_ahead else 0.5 * (tx + as_float(mp_image(tx, rx1, rx2, d1, d2)))
    assert np.max(np.abs(result.position - truth)) <= tolerance(result, tx, rx1, rx2, d1, d2, ulps=64)
