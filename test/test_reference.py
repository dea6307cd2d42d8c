"""The papers' formulas (sonar_ring.reference) against exact geometry and the production path."""

import numpy as np
import pytest
from numpy.testing import assert_allclose

from sonar_ring import localise as loc
from sonar_ring.amplitude_rules import fuse, fusion_weights
from sonar_ring.geometry import load_layout
from sonar_ring.reference import barshan_kuc, browne

LD = np.longdouble
RING_RADIUS = 0.31
SEPARATION = 0.04


def norm(v):
    return np.sqrt(np.sum(np.square(v), axis=-1))


def browne_pair():
    ring = load_layout("browne_ring")
    rx = ring.group_receivers()[0, :, :2]
    return ring.transmitters[0, :2], rx[0], rx[1]


def browne_grid(stride_x, stride_y):
    """Browne's 1 mm grid (0.01-5.7 m ahead, +-1 m aside) in the pair frame, subsampled."""
    ahead = np.unique(np.r_[np.arange(10, 5701, stride_x), 5700]) / 1000.0
    side = np.unique(np.r_[np.arange(-1000, 1001, stride_y), 1000]) / 1000.0
    x, y = np.meshgrid(RING_RADIUS + ahead, side, indexing="ij")
    return np.stack([x, y], axis=-1).reshape(-1, 2)


GRID = browne_grid(41, 29)


def corner_paths(tx, rx1, rx2, point):
    image = 2 * point.astype(LD) - tx.astype(LD)
    return norm(image - rx1.astype(LD)).astype(float), norm(image - rx2.astype(LD)).astype(float)


def edge_paths(tx, rx1, rx2, point):
    p = point.astype(LD)
    k = norm(p - tx.astype(LD))
    return (k + norm(p - rx1.astype(LD))).astype(float), (k + norm(p - rx2.astype(LD))).astype(float)


# --------------------------------------------------------------------------- Browne

def test_browne_layout_matches_the_reference_frame():
    tx, rx1, rx2 = browne_pair()
    assert_allclose(tx, [0.0, 0.0])
    assert_allclose(rx1, [RING_RADIUS, SEPARATION / 2])
    assert_allclose(rx2, [RING_RADIUS, -SEPARATION / 2])


def test_bearing_eqs_4_and_8_agree_with_production_where_well_conditioned():
    d1 = np.linspace(0.5, 10.0, 40)[:, None]
    phi = np.radians(np.linspace(-60, 60, 25))
    rx1, rx2 = np.array([0.0, 0.02]), np.array([0.0, -0.02])
    image = rx1 + d1[..., None] * np.stack([np.cos(phi), np.sin(phi)], axis=-1)
    d2 = norm(image - rx2)
    d1 = np.broadcast_to(d1, d2.shape)
    assert_allclose(browne.bearing_eq4(d1, d2, SEPARATION), loc.bearing(d1, d2, SEPARATION).value, atol=1e-12)
    assert_allclose(browne.bearing_eq8(d1, d2, SEPARATION), loc.bearing(d1, d2, SEPARATION, exact=False).value,
                    atol=1e-15)


def test_trigonometric_chain_is_exact_geometry():
    """Eqs 9-19: y = |TG| (half of |TT'|), r = |TX|, theta and psi the directions of G and X."""
    tx, rx1, rx2 = browne_pair()
    d1, d2 = corner_paths(tx, rx1, rx2, GRID)
    chain = browne.plane_chain(d1, d2, SEPARATION, RING_RADIUS)
    assert_allclose(chain["S"], norm(rx1 - tx), rtol=1e-15)
    assert_allclose(chain["y"], norm(GRID - tx), atol=1e-11)
    assert_allclose(chain["theta"], np.arctan2(GRID[:, 1], GRID[:, 0]), atol=1e-12)
    plane = loc.plane(tx, rx1, rx2, d1, d2)
    reflection = plane.reflection_points[:, 0]
    assert_allclose(chain["r"], norm(reflection - tx), atol=1e-11)
    assert_allclose(chain["psi"], np.arctan2(reflection[:, 1], reflection[:, 0]), atol=1e-12)


@pytest.mark.parametrize("model", ["plane", "corner", "edge"])
def test_production_agrees_with_browne_on_his_grid(model):
    tx, rx1, rx2 = browne_pair()
    if model == "edge":
        d1, d2 = edge_paths(tx, rx1, rx2, GRID)
        paper = browne.edge_point(d1, d2, SEPARATION, RING_RADIUS)
        production = loc.edge(tx, rx1, rx2, d1, d2).position
        tolerance = 1e-9  # the closed form's rounding grows with range (see bench/results/localise.md)
    else:
        d1, d2 = corner_paths(tx, rx1, rx2, GRID)
        if model == "plane":
            paper = browne.plane_point(d1, d2, SEPARATION, RING_RADIUS)
            production = loc.plane(tx, rx1, rx2, d1, d2).reflection_points[:, 0]
        else:
            paper = browne.corner_point(d1, d2, SEPARATION, RING_RADIUS)
            production = loc.corner(tx, rx1, rx2, d1, d2).position
        tolerance = 1e-11
    assert np.all(np.isfinite(paper))
    assert np.max(norm(paper - production)) < tolerance


def test_appendix_a_pairs_and_selection():
    """The second solution (x2, y2, h2) is the edge in front on Browne's grid; h is the emitter distance k."""
    tx, rx1, rx2 = browne_pair()
    d1, d2 = edge_paths(tx, rx1, rx2, GRID)
    x1, y1, h1, x2, y2, h2 = browne.edge_solutions(d1, d2, SEPARATION, RING_RADIUS)
    assert np.all(x2 > 0) and np.all(x1 < 0)
    truth = GRID - [RING_RADIUS, 0.0]  # Fig. 8 frame: origin between the receivers, R1 at y = -E
    assert_allclose(x2, truth[:, 0], atol=1e-9)
    assert_allclose(y2, -truth[:, 1], atol=1e-9)
    assert_allclose(h2, norm(GRID - tx), atol=1e-9)
    # the other solution also satisfies eqs 21-24: an edge behind the emitter
    k = h1
    assert_allclose(x1**2 + (y1 + SEPARATION / 2) ** 2, (d1 - k) ** 2, rtol=1e-6)
    assert_allclose(x1**2 + (y1 - SEPARATION / 2) ** 2, (d2 - k) ** 2, rtol=1e-6)
    assert_allclose((x1 + RING_RADIUS) ** 2 + y1**2, k**2, rtol=1e-6)


def test_appendix_a_drifts_with_range_where_production_does_not():
    tx, rx1, rx2 = browne_pair()
    far = np.array([[RING_RADIUS + 5.7, y] for y in np.linspace(-1, 1, 41)])
    d1, d2 = edge_paths(tx, rx1, rx2, far)
    paper = norm(browne.edge_point(d1, d2, SEPARATION, RING_RADIUS) - far)
    production = norm(loc.edge(tx, rx1, rx2, d1, d2).position - far)
    assert np.max(production) < 1e-12
    assert np.max(paper) > 10 * np.max(production)


def test_eq26_is_the_exact_correction_for_a_plane_facing_the_pair():
    """Eq 25 unfolds the head-on plane; production's horizontal path gives the same range."""
    distance = np.linspace(0.05, 5.0, 50)  # receivers to the plane
    for height in (0.08, 0.125):
        t = np.hypot(RING_RADIUS + 2 * distance, height)
        assert_allclose(browne.vertical_eq26(t, height, RING_RADIUS), distance, rtol=1e-13)
        corrected = loc.horizontal_path(t, height).value
        assert_allclose((corrected - RING_RADIUS) / 2, distance, rtol=1e-13)
    # an inclined wall: eq 26's d is no longer the distance along the pair's axis
    wall_normal = np.array([np.cos(0.3), np.sin(0.3)])
    for height in (0.08, 0.125):
        tx = np.zeros(2)
        rx = np.array([RING_RADIUS, 0.0])
        image = tx + 2 * (1.0 - tx @ wall_normal) * wall_normal
        t = np.hypot(norm(image - rx), height)
        estimate = browne.vertical_eq26(t, height, RING_RADIUS)
        axis_distance = 1.0 / np.cos(0.3) - RING_RADIUS
        assert abs(estimate - axis_distance) > 0.01
        assert_allclose(loc.horizontal_path(t, height).value, norm(image - rx), rtol=1e-14)


# --------------------------------------------------------------------------- Barshan & Kuc

THETA = np.radians(np.linspace(-10, 10, 41))
R = 0.8
D_BK = 0.08
A = np.array([0.0, D_BK / 2])
B = np.array([0.0, -D_BK / 2])


def exact_plane_ranges(r, theta, d):
    """One-way ranges of a plane at perpendicular distance r, normal at theta (mirror images)."""
    normal = np.stack([np.cos(theta), np.sin(theta)], axis=-1)
    a, b = np.array([0.0, d / 2]), np.array([0.0, -d / 2])
    r_aa = r - normal @ a
    r_bb = r - normal @ b
    b_image = b + 2 * (r - normal @ b)[..., None] * normal
    return r_aa, r_bb, norm(a - b_image) / 2


def test_barshan_kuc_range_equations():
    r_aa, r_bb, r_ab = exact_plane_ranges(R, THETA, D_BK)
    paper = barshan_kuc.plane_ranges(R, THETA, D_BK)
    assert_allclose(paper[0], r_aa, atol=1e-15)  # eq 15
    assert_allclose(paper[1], r_bb, atol=1e-15)  # eq 16
    # eq 17 is the corner's range again: right at normal incidence only, first order in theta elsewhere
    assert_allclose(r_ab, np.sqrt(R**2 + D_BK**2 * np.cos(THETA) ** 2 / 4), rtol=1e-15)
    assert_allclose(paper[2][THETA == 0], r_ab[THETA == 0], rtol=1e-15)
    assert_allclose(paper[2] - r_ab, -D_BK / 2 * np.sin(THETA), atol=2e-4)
    apex = R * np.stack([np.cos(THETA), np.sin(THETA)], axis=-1)
    corner = barshan_kuc.corner_ranges(R, THETA, D_BK)
    assert_allclose(corner[0], norm(apex - A), rtol=1e-15)  # eq 18
    assert_allclose(corner[1], norm(apex - B), rtol=1e-15)  # eq 19
    assert_allclose(corner[2], norm(apex), rtol=1e-15)  # eq 20


def test_plane_inclination_eq21_agrees_with_production():
    r_aa, r_bb, r_ab = exact_plane_ranges(R, THETA, D_BK)
    paper = barshan_kuc.plane_inclination(r_aa, r_bb, D_BK)
    assert_allclose(paper, THETA, atol=1e-13)
    production = loc.plane(A, A, B, 2 * r_aa, 2 * r_ab)
    assert_allclose(np.arctan2(production.normal[:, 1], production.normal[:, 0]), paper, atol=1e-13)


def test_corner_inclination_eq22_as_printed():
    """Eq 22 returns about asin(sin(theta) / 2), with the sign lost on its second branch."""
    r_aa, r_bb, r_ab = barshan_kuc.corner_ranges(R, THETA, D_BK)
    paper = barshan_kuc.corner_inclination(r_aa, r_bb, r_ab, D_BK)
    assert_allclose(barshan_kuc.corner_correction(R, D_BK), np.sqrt(R**2 + D_BK**2 / 4) - R, rtol=1e-15)
    nonzero = THETA != 0
    assert_allclose(paper[nonzero], np.arcsin(np.abs(np.sin(THETA[nonzero])) / 2), atol=1e-3)
    production = loc.corner(A, A, B, 2 * r_aa, 2 * r_ab)
    assert_allclose(np.arctan2(production.position[:, 1], production.position[:, 0]), THETA, atol=1e-13)


def test_fusion_weights_eq41():
    variances = np.array([np.radians(1.85) ** 2, np.radians(2.5) ** 2, np.radians(4.0) ** 2])
    weights = barshan_kuc.optimal_weights(variances)
    assert_allclose(weights.sum(), 1.0, rtol=1e-15)
    assert_allclose(fusion_weights(variances), weights, rtol=1e-15)
    # eq 36 at the optimum equals 1 / sum(1 / sigma^2) (eq 40: lambda = -2 / sum)
    assert_allclose(np.sum(weights**2 * variances), 1 / np.sum(1 / variances), rtol=1e-14)
    _, variance = fuse(np.radians([1.0, 2.0, 3.0]), variances)
    assert_allclose(variance, 1 / np.sum(1 / variances), rtol=1e-15)


def test_error_handling():
    """The reference formulas do no checking: invalid data come back as NaN, never as an exception."""
    with np.errstate(invalid="ignore", divide="ignore"):
        assert np.isnan(browne.bearing_eq4(1.0, 2.0, SEPARATION))
        assert np.isnan(browne.bearing_eq8(1.0, 2.0, SEPARATION))
        assert np.isnan(browne.vertical_eq26(0.05, 0.08, RING_RADIUS))
        assert np.all(np.isnan(browne.edge_point(1.0, 2.0, SEPARATION, RING_RADIUS)))
        assert np.isnan(barshan_kuc.plane_inclination(1.0, 2.0, D_BK))
    # eq 22 at exactly zero inclination: both branches fail by rounding (R_bb' - s == R_ab' only exactly)
    r = barshan_kuc.corner_ranges(R, 0.0, D_BK)
    value = barshan_kuc.corner_inclination(*r, D_BK)
    assert np.isnan(value) or abs(value) < 1e-7
