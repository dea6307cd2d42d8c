"""Classifier core: Barshan & Kuc's numbers, amplitude rules on the analytic curves, fusion,
inclination and the geometric consistency test on exact ring geometry."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal

from sonar_ring import classify, localise
from sonar_ring.classify import (
    CORNER,
    EDGE,
    PLANE,
    UNKNOWN,
    amplitude_rule,
    choose_pair,
    classify_amplitudes,
    corner_inclination,
    fuse,
    fusion_weights,
    geometric_consistency,
    inclination_variance,
    plane_inclination,
    separation_limits,
    working_range,
)
from sonar_ring.geometry import beam_half_angle, load_layout
from sonar_ring.simulate import Noise, Simulator, load_scene

# Barshan & Kuc (1990), section V: lambda = 5.72 mm, a = 20 mm, d = 80 mm, sigma = 2 % of A_max.
WAVELENGTH = 5.72e-3
APERTURE = 20e-3
SEPARATION = 0.080
SIGMA_REL = 0.02
THETA0_PAPER = math.radians(10.0)
THETA0 = float(beam_half_angle(WAVELENGTH, APERTURE))


def analytic_amplitudes(cls, inclination, range_m, separation=SEPARATION, theta0=THETA0):
    """Eqs 6-11 (A_max = 1): A_aa', A_ab' (= A_ba'), A_bb' for a plane or a corner."""
    theta_s = np.arctan(separation / (2 * range_m))  # eq 8
    gauss = lambda angle: np.exp(-4 * np.square(angle) / theta0**2)  # noqa: E731
    if cls == PLANE:
        return gauss(inclination), gauss(theta_s) * gauss(inclination), gauss(inclination)  # eqs 6-7
    return gauss(inclination - theta_s), gauss(inclination), gauss(inclination + theta_s)  # eqs 9-11


# --------------------------------------------------------------------------- the paper's numbers

def test_beam_half_angle_is_10_degrees_eq2():
    # asin(0.61 * 5.72 / 20) = 10.047 deg; the paper rounds it to 10 deg.
    assert_allclose(math.degrees(THETA0), 10.0, atol=0.05)


def test_working_range_eqs_28_29_for_the_papers_pair():
    # eq 28: 0.08 / (2 tan 10 deg) = 0.22685 m
    # eq 29: 2 * 0.08 / (tan 10 deg * sqrt(-ln(1 - 0.12))) = 0.16 / (0.176327 * 0.357535) = 2.53793 m
    r_min, r_max = working_range(SEPARATION, THETA0_PAPER, SIGMA_REL)
    assert_allclose(r_min, 0.226851, rtol=1e-5)
    assert_allclose(r_max, 2.537927, rtol=1e-5)
    # The experiment's 200-1600 mm starts just short of R_min and ends well inside R_max.
    assert r_min > 0.200 and r_max > 1.600


def test_separation_limits_eqs_26_27_and_their_inverse():
    ranges = np.array([0.2, 0.3, 1.0, 1.6])
    d_min, d_max = separation_limits(ranges, THETA0_PAPER, SIGMA_REL)
    # eq 26 at R = 1 m: tan(10 deg) / 2 * 0.357535 = 0.031522 m; eq 27: 2 tan(10 deg) = 0.352654 m
    assert_allclose(d_min[2], 0.031522, rtol=1e-4)
    assert_allclose(d_max, 2 * ranges * math.tan(THETA0_PAPER), rtol=1e-12)
    for rule in classify.MARGIN_RULES:
        d_min, d_max = separation_limits(ranges, THETA0, SIGMA_REL, margin_rule=rule)
        # A pair of separation d_max(R) starts working at R, one of d_min(R) stops working at R.
        assert_allclose(working_range(d_max, THETA0, SIGMA_REL, margin_rule=rule)[0], ranges, rtol=1e-12)
        assert_allclose(working_range(d_min, THETA0, SIGMA_REL, margin_rule=rule)[1], ranges, rtol=1e-12)


def test_eq26_as_printed_leaves_less_than_the_6_sigma_margin_of_eqs_24_25():
    # Eqs 24-25 ask for A_aa'(0) - A_ab'(0) >= 6 sigma; with eqs 6-8 that is met with
    # equality exactly at the amplitude-model R_max, while the printed eq 26/29 puts
    # R_max twice as far, where the gap is only about a quarter of it (theta_s is halved).
    def gap_at_normal_incidence(range_m):
        a_aa, a_ab, _ = analytic_amplitudes(PLANE, 0.0, range_m)
        return a_aa - a_ab

    _, r_max_model = working_range(SEPARATION, THETA0, SIGMA_REL, margin_rule="amplitude_model")
    _, r_max_paper = working_range(SEPARATION, THETA0, SIGMA_REL)
    assert_allclose(gap_at_normal_incidence(r_max_model), 6 * SIGMA_REL, rtol=1e-12)
    assert_allclose(r_max_paper / r_max_model, 2 * THETA0 / math.tan(THETA0), rtol=2e-3)
    assert_allclose(gap_at_normal_incidence(r_max_paper), 1 - (1 - 6 * SIGMA_REL) ** 0.25, rtol=0.03)


def test_pair_choice_eq30_on_the_six_transducer_array():
    array = load_layout("barshan_kuc_array")
    separations = array.group_separation()
    assert_allclose(separations, [0.04, 0.12, 0.20], atol=1e-12)
    # (d_min + d_max) / 2 = 0.0576 m at 0.3 m, 0.1153 m at 0.6 m, 0.1921 m at 1 m
    assert_array_equal(choose_pair(separations, [0.3, 0.6, 1.0], THETA0_PAPER, SIGMA_REL), [0, 1, 2])


def test_fusion_weights_eq41():
    assert_allclose(fusion_weights([1.0, 4.0, 4.0]), [2 / 3, 1 / 6, 1 / 6], rtol=1e-12)
    assert_allclose(fusion_weights([[2.0, 2.0], [1.0, 3.0]]), [[0.5, 0.5], [0.75, 0.25]], rtol=1e-12)
    # The weights minimise sum w_i^2 sigma_i^2 (eq 36) under sum w_i = 1 (eq 32): any
    # feasible perturbation increases it, and the minimum is 1 / sum(1 / sigma_i^2) (eq 40).
    variances = np.array([1.85, 3.0, 5.0]) ** 2
    weights = fusion_weights(variances)
    best = np.sum(weights**2 * variances)
    assert_allclose(best, 1 / np.sum(1 / variances), rtol=1e-12)
    rng = np.random.default_rng(41)
    perturbation = rng.normal(size=(200, 3))
    perturbation -= perturbation.mean(axis=1, keepdims=True)
    assert np.all(np.sum((weights + 0.01 * perturbation) ** 2 * variances, axis=1) > best)


def test_fused_estimate_has_the_predicted_spread():
    rng = np.random.default_rng(7)
    sigmas = np.radians([1.85, 3.0, 5.0])
    truth = math.radians(4.0)
    estimates = truth + rng.normal(size=(20000, 3)) * sigmas
    fused, variance = fuse(estimates, sigmas**2)
    assert_allclose(variance, 1 / np.sum(1 / sigmas**2), rtol=1e-12)
    assert_allclose(np.std(fused), math.sqrt(variance[0]), rtol=0.03)
    assert_allclose(np.mean(fused), truth, atol=3 * math.sqrt(variance[0] / 20000))
    assert np.std(fused) < np.std(estimates[:, 0])


# --------------------------------------------------------------------------- amplitude rules

def test_amplitude_rule_decisions_and_confidence():
    sigma = 0.02
    step = sigma * math.sqrt(1.5)  # standard deviation of direct minus mean cross amplitude
    # PLANE: min(A_aa', A_bb') - cross = 6 sigma + 2 steps -> margin 2, confidence 0.9545.
    # CORNER: cross - min(A_aa', A_bb') = 6 sigma + 1 step (eq 14's OR needs only one of the two).
    # Differences of only 5 sigma, and a NaN, decide nothing.
    amplitude = np.array([
        [[1.0, 0.88 - 2 * step], [0.88 - 2 * step, 1.0]],
        [[0.5, 0.62 + step], [0.62 + step, 1.0]],
        [[1.0, 0.9], [0.9, 1.0]],
        [[1.0, np.nan], [0.5, 1.0]],
    ])
    result = classify_amplitudes(amplitude, sigma)
    assert_array_equal(result.cls, [PLANE, CORNER, UNKNOWN, UNKNOWN])
    assert_allclose(result.margin, [2.0, 1.0, 0.0, 0.0], rtol=1e-9)
    assert_allclose(result.confidence, [0.954500, 0.682689, 0.0, 0.0], atol=1e-6)
    assert result.cls.dtype == np.uint8
    assert_array_equal(amplitude_rule(*amplitude[:, [0, 0, 1, 1], [0, 1, 0, 1]].T, sigma), result.cls)


def test_amplitude_rule_on_the_noise_free_analytic_curves():
    # Eqs 6-11 over ranges and inclinations, beyond the beam as well: the rule says PLANE
    # for plane curves exactly where both margins of eq 13 exceed 6 sigma, CORNER for
    # corner curves where eq 14 holds, and never the other class.
    sigma = SIGMA_REL
    ranges = np.linspace(0.2, 3.0, 29)[:, None]
    inclinations = np.radians(np.linspace(-20, 20, 81))[None, :]
    for cls, other in ((PLANE, CORNER), (CORNER, PLANE)):
        a_aa, a_cross, a_bb = analytic_amplitudes(cls, inclinations, ranges)
        codes = amplitude_rule(a_aa, a_cross, a_cross, a_bb, sigma)
        if cls == PLANE:
            expected = (a_aa - a_cross > 6 * sigma) & (a_bb - a_cross > 6 * sigma)
        else:
            expected = (a_cross - a_aa > 6 * sigma) | (a_cross - a_bb > 6 * sigma)
        assert_array_equal(codes == cls, expected)
        assert not np.any(codes == other)
        # Near normal incidence and inside the amplitude-model working range both decide.
        _, r_max = working_range(SEPARATION, THETA0, SIGMA_REL, margin_rule="amplitude_model")
        near = (np.abs(inclinations) <= math.radians(2)) & (ranges < 0.8 * r_max)
        assert np.all(codes[np.broadcast_to(near, codes.shape)] == cls)


def test_amplitude_rule_with_noise_keeps_the_3_sigma_promise():
    # sigma = 2 % additive Gaussian noise on eqs 6-11, |theta| <= 10 deg, ranges inside
    # the working range: >= 99.7 % of the decisions are right; beyond the beam the rule
    # abstains rather than errs.
    rng = np.random.default_rng(1990)
    trials = 2000
    ranges = np.array([0.3, 0.6, 1.0, 1.4, 2.0])[:, None, None]
    inside = np.radians(np.arange(-10, 10.1, 2.5))[None, :, None]
    outside = np.radians([-15.0, -12.5, 12.5, 15.0])[None, :, None]
    for cls in (PLANE, CORNER):
        for inclinations, within in ((inside, True), (outside, False)):
            a_aa, a_cross, a_bb = analytic_amplitudes(cls, inclinations, ranges)
            shape = np.broadcast_shapes(a_aa.shape, a_cross.shape, a_bb.shape, (1, 1, trials))
            noisy = [np.broadcast_to(a, shape) + rng.normal(0, SIGMA_REL, shape)
                     for a in (a_aa, a_cross, a_cross, a_bb)]
            codes = amplitude_rule(*noisy, SIGMA_REL)
            decided = codes != UNKNOWN
            correct = codes == cls
            if within:
                assert correct.sum() / decided.sum() >= 0.997
                # At normal incidence up to 1 m (gap >= 0.19 = 9.4 sigma) nearly all decide.
                assert correct[:3, 4].mean() >= 0.95
            assert (decided & ~correct).mean() <= 1e-3


def test_confidence_is_the_gaussian_mass_within_the_margin():
    margins = np.array([0.0, 0.5, 1.0, 2.0, 3.0, 6.0])
    expected = [math.erf(m / math.sqrt(2)) for m in margins]
    assert_allclose(classify.confidence_from_margin(margins), expected, atol=2e-7)
    assert_array_equal(classify.confidence_from_margin([-1.0, np.nan]), [0.0, 0.0])
    flat = classify.confidence_from_margin(margins)
    for grid in (margins.reshape(2, 3), margins.reshape(3, 2).T):  # any shape and memory order, kept
        assert_array_equal(classify.confidence_from_margin(grid), flat[np.searchsorted(margins, grid)])
    assert classify.confidence_from_margin(3.0).shape == ()


@settings(max_examples=200, deadline=None)
@given(amplitudes=st.lists(st.floats(0.0, 1.2), min_size=4, max_size=4),
       sigma=st.floats(1e-3, 0.1), scale=st.floats(0.1, 10.0))
def test_amplitude_rule_is_mirror_symmetric_and_scale_free(amplitudes, sigma, scale):
    a_aa, a_ab, a_ba, a_bb = amplitudes
    code = amplitude_rule(a_aa, a_ab, a_ba, a_bb, sigma)
    # Swapping the transducers (a <-> b) mirrors the scene; the class is the same.
    assert amplitude_rule(a_bb, a_ba, a_ab, a_aa, sigma) == code
    # Only amplitude ratios to sigma matter; multiply by a power of two to stay exact.
    factor = 2.0 ** round(math.log2(scale))
    assert amplitude_rule(a_aa * factor, a_ab * factor, a_ba * factor, a_bb * factor, sigma * factor) == code


def test_amplitude_rule_needs_reciprocal_cross_amplitudes():
    # A_ab' and A_ba' travel one path in opposite directions; 0.2 apart they are not one echo.
    assert amplitude_rule(1.0, 0.6, 0.4, 1.0, 0.02) == UNKNOWN
    assert amplitude_rule(1.0, 0.55, 0.45, 1.0, 0.02) == PLANE


# --------------------------------------------------------------------------- inclination

def pair_ranges(cls, inclination, range_m, separation=SEPARATION):
    """Exact one-way ranges R_aa', R_ab', R_bb' from geometry (a at +y, b at -y)."""
    a = np.array([0.0, separation / 2])
    b = -a
    direction = np.stack([np.cos(inclination), np.sin(inclination)], axis=-1)
    if cls == PLANE:
        # Perpendicular distances (range_m is the centre's); cross path via the image of a.
        r_aa = range_m - direction @ a
        r_bb = range_m - direction @ b
        image = a + 2 * r_aa[..., None] * direction
        r_ab = np.linalg.norm(image - b, axis=-1) / 2
        return r_aa, r_ab, r_bb
    apex = range_m * direction  # eqs 18-20: the corner is a retro-reflector about its apex
    r_ab = np.full(inclination.shape, float(range_m))
    return np.linalg.norm(apex - a, axis=-1), r_ab, np.linalg.norm(apex - b, axis=-1)


def test_plane_inclination_eq21_is_exact():
    inclination = np.radians(np.linspace(-15, 15, 31))
    for range_m in (0.2, 1.0, 1.6):
        r_aa, _, r_bb = pair_ranges(PLANE, inclination, range_m)
        assert_allclose(plane_inclination(r_aa, r_bb, SEPARATION), inclination, atol=1e-12)


def test_corner_inclination_eqs_22_23_against_exact_geometry():
    inclination = np.radians(np.linspace(-15, 15, 31))
    for range_m, tolerance_deg in ((0.3, 0.40), (1.0, 0.10), (1.6, 0.06)):
        r_aa, r_ab, r_bb = pair_ranges(CORNER, inclination, range_m)
        estimate = corner_inclination(r_aa, r_ab, r_bb, SEPARATION)
        assert_allclose(np.degrees(estimate), np.degrees(inclination), atol=tolerance_deg)
        assert estimate[15] == 0.0  # s makes theta_c vanish at zero inclination (eq 23)
        # As printed, eq 22 (no factor 2, no sign in its second branch) returns |theta| / 2.
        s = np.sqrt(r_ab**2 + SEPARATION**2 / 4) - r_ab
        printed = np.where(r_bb - s >= r_ab, np.arcsin((r_bb - s - r_ab) / SEPARATION),
                           np.arcsin((r_aa - s - r_ab) / SEPARATION))
        assert_allclose(np.degrees(printed), np.degrees(np.abs(inclination)) / 2, atol=0.35)


def test_inclinations_agree_with_the_virtual_image():
    # The exact inclination: localise the virtual image T' of transmitter a from its two
    # echoes (a -> a, a -> b); a plane's normal points along T' - a, a corner's apex is
    # (a + T') / 2.  Eq 21 matches it exactly, corrected eq 22 to its approximation error.
    a, b = np.array([0.0, SEPARATION / 2]), np.array([0.0, -SEPARATION / 2])
    inclination = np.radians(np.linspace(-15, 15, 31))
    for range_m in (0.3, 1.0, 1.6):
        for cls in (PLANE, CORNER):
            r_aa, r_ab, r_bb = pair_ranges(cls, inclination, range_m)
            image = localise.virtual_image(a, a, b, 2 * r_aa, 2 * r_ab)
            assert image.valid.all()
            if cls == PLANE:
                normal = image.position - a
                exact = np.arctan2(normal[:, 1], normal[:, 0])
                estimate = plane_inclination(r_aa, r_bb, SEPARATION)
                tolerance = 1e-9
            else:
                apex = 0.5 * (a + image.position)
                exact = np.arctan2(apex[:, 1], apex[:, 0])
                estimate = corner_inclination(r_aa, r_ab, r_bb, SEPARATION)
                tolerance = math.radians(0.4)
            assert_allclose(exact, inclination, atol=1e-9)
            assert_allclose(estimate, exact, atol=tolerance)


def test_inclination_variance_matches_monte_carlo():
    rng = np.random.default_rng(21)
    range_sigma = 0.5e-3
    inclination = math.radians(6.0)
    trials = 40000
    for cls in (PLANE, CORNER):
        r_aa, r_ab, r_bb = (r + range_sigma * rng.normal(size=trials)
                            for r in pair_ranges(cls, np.full(trials, inclination), 1.0))
        estimate = (plane_inclination(r_aa, r_bb, SEPARATION) if cls == PLANE
                    else corner_inclination(r_aa, r_ab, r_bb, SEPARATION))
        predicted = inclination_variance(SEPARATION, range_sigma, inclination, cls)
        assert_allclose(np.var(estimate), predicted, rtol=0.05)


# --------------------------------------------------------------------------- geometric consistency

SPEED = 343.0
SIGMA_PATH = SPEED * 1e-6  # sigma_t = 1 us


def ring_receivers(pairs=(0, 1)):
    """Horizontal receiver positions of adjacent pairs of Browne's ring, shape (2 * len(pairs), 2)."""
    ring = load_layout("browne_ring")
    return ring.receivers[ring.groups[list(pairs)].reshape(-1), :2]


def exact_paths(cls, receivers, range_m, bearing):
    """Horizontal paths from the ring centre via a plane (normal along bearing), corner or edge."""
    direction = np.stack([np.cos(bearing), np.sin(bearing)], axis=-1)
    if cls == EDGE:
        point = range_m * direction
        return (np.linalg.norm(point, axis=-1)[:, None]
                + np.linalg.norm(point[:, None, :] - receivers[None], axis=-1))
    image = 2 * range_m * direction  # plane: mirror image; corner: 2C - T with C = range * direction
    return np.linalg.norm(image[:, None, :] - receivers[None], axis=-1)


def test_consistency_recovers_the_exact_models():
    receivers = ring_receivers((47, 0, 1))
    bearing = np.radians([-5.0, 0.0, 3.0, 7.5])
    for cls in (PLANE, CORNER, EDGE):
        paths = exact_paths(cls, receivers, 0.6, bearing)
        result = geometric_consistency([0.0, 0.0], np.broadcast_to(receivers, (4, 6, 2)), paths, SIGMA_PATH)
        direction = np.stack([np.cos(bearing), np.sin(bearing)], axis=-1)
        # With exact data every pair of receivers agrees with the least-squares fit.
        tx = np.zeros((4, 2))
        pair_solution = (localise.edge if cls == EDGE else localise.virtual_image)(
            tx, receivers[2], receivers[3], paths[:, 2], paths[:, 3])
        fitted = result.edge_position if cls == EDGE else result.virtual_image
        assert_allclose(fitted, pair_solution.position, atol=1e-9)
        if cls == EDGE:
            assert_allclose(result.edge_position, 0.6 * direction, atol=1e-9)
            assert_allclose(result.chi2_edge, 0.0, atol=1e-9)
            assert_array_equal(result.cls, EDGE)
            assert not result.specular.any()
        else:
            assert_allclose(result.virtual_image, 1.2 * direction, atol=1e-9)
            assert_allclose(result.chi2_specular, 0.0, atol=1e-9)
            assert_array_equal(result.cls, UNKNOWN)  # plane or corner: geometry cannot tell which
            assert result.specular.all()
        assert np.all(result.confidence > 0.99) and np.all(result.margin > 3)
        assert_array_equal(result.dof, 4)


def test_consistency_false_decisions_stay_below_1_percent():
    # Noise sigma_t = 1 us on every receiver of two overlapping pairs; ranges from where
    # the test is decisive to where it cannot be.  Decisions for the wrong model stay
    # well under 1 %, and the true model's chi-square follows chi-square with 2 dof.
    rng = np.random.default_rng(2011)
    receivers = ring_receivers((0, 1))
    trials = 3000
    bearing = np.radians(rng.uniform(0.0, 7.5, trials))
    for range_m, decisive in ((0.5, True), (1.0, False), (2.5, False)):
        for cls in (PLANE, EDGE):
            paths = exact_paths(cls, receivers, range_m, bearing) + rng.normal(0, SIGMA_PATH, (trials, 4))
            result = geometric_consistency(np.zeros(2), np.broadcast_to(receivers, (trials, 4, 2)),
                                           paths, SIGMA_PATH)
            right = result.specular if cls == PLANE else result.cls == EDGE
            wrong = result.cls == EDGE if cls == PLANE else result.specular
            assert wrong.mean() < 0.01
            if decisive:
                assert right.mean() > 0.98
            chi2_true = result.chi2_specular if cls == PLANE else result.chi2_edge
            assert_allclose(np.mean(chi2_true), 2.0, rtol=0.1)
    # Far away the two models coincide and the test abstains.
    assert (result.cls == UNKNOWN).mean() > 0.95 and result.specular.mean() < 0.05


def test_consistency_fits_reach_the_least_squares_minimum():
    # Noisy echoes: Gauss-Newton converges only linearly, and the fit stops on the chi-square's
    # decrease (_CONVERGED), not on the step.  The model that fits must still report the chi-square
    # and position of the weighted least-squares minimum, found here by scipy's Levenberg-Marquardt.
    least_squares = pytest.importorskip("scipy.optimize").least_squares
    rng = np.random.default_rng(5)
    receivers = ring_receivers((47, 0, 1))
    trials = 40

    def residuals(point, measured, sigma, edge):
        emitter = np.linalg.norm(point) if edge else 0.0
        return (emitter + np.linalg.norm(point - receivers, axis=-1) - measured) / sigma

    for cls, range_m, sigma in ((PLANE, 0.3, SIGMA_PATH), (EDGE, 1.0, SIGMA_PATH), (PLANE, 2.5, 5 * SIGMA_PATH)):
        bearing = np.radians(rng.uniform(-7.5, 7.5, trials))
        paths = exact_paths(cls, receivers, range_m, bearing) + rng.normal(0, sigma, (trials, 6))
        result = geometric_consistency(np.zeros(2), np.broadcast_to(receivers, (trials, 6, 2)), paths, sigma)
        fitted, chi2 = ((result.edge_position, result.chi2_edge) if cls == EDGE
                        else (result.virtual_image, result.chi2_specular))
        for n in range(trials):
            reference = least_squares(residuals, fitted[n], args=(paths[n], sigma, cls == EDGE), method="lm",
                                      xtol=1e-15, ftol=1e-15, gtol=1e-15)
            assert_allclose(chi2[n], np.sum(reference.fun ** 2), atol=1e-6)
            assert_allclose(fitted[n], reference.x, atol=1e-6)


def test_consistency_abstains_when_neither_model_fits():
    receivers = ring_receivers((0, 1))
    paths = exact_paths(PLANE, receivers, 0.5, np.radians([2.0]))
    paths[0, 3] += 0.05  # one receiver heard something else, 5 cm further
    result = geometric_consistency(np.zeros(2), receivers[None], paths, SIGMA_PATH)
    assert result.cls[0] == UNKNOWN and not result.specular[0]
    assert result.confidence[0] == 0.0 and result.margin[0] == 0.0
    assert result.chi2_specular[0] > 1e3 and result.chi2_edge[0] > 1e3


def test_overlapping_groups_of_the_ring_are_two_on_each_side():
    ring = load_layout("browne_ring")
    neighbours = classify.overlapping_groups(ring)  # facings 7.5 deg apart, +-10 deg acceptance
    assert neighbours.shape == (48, 4)
    assert_array_equal(neighbours[0], [1, 47, 2, 46])
    assert_array_equal(np.sort(neighbours[10]), [8, 9, 11, 12])


def test_ring_consistency_on_a_triad_with_its_emitter_beside_the_receivers():
    # Kreczmer's triad: one emitter 20 mm above the receiver line, echoes from +x.  The
    # far-field start must come from the facing, not from emitter -> receivers (along -y).
    triad = load_layout("kreczmer_triad")
    receivers = triad.receivers[triad.groups[0], :2]
    tx = triad.transmitters[0, :2]
    bearing = np.radians([-20.0, 0.0, 30.0])
    normal = np.stack([np.cos(bearing), np.sin(bearing)], axis=-1)
    image = tx + 2 * (0.8 - normal @ tx)[:, None] * normal  # walls 0.8 m from the origin
    horizontal = np.linalg.norm(image[:, None, :] - receivers[None], axis=-1)
    paths = np.sqrt(horizontal**2 + triad.height_offset()[0, 0] ** 2)
    result = classify.ring_consistency(triad, np.zeros(3, int), paths, 343.0 * 0.33e-6)
    assert_allclose(result.virtual_image, image, atol=1e-9)
    assert_array_equal(result.dof, 1)
    assert_array_equal(result.cls, UNKNOWN)  # 15 mm of aperture cannot see the curvature


def test_ring_consistency_leaves_out_a_group_flooded_with_echoes():
    """Thousands of echoes in one pair (firmware gone wrong) cost linear memory and leave the others alone."""
    ring = load_layout("browne_ring")
    scene = load_scene("room")
    ping = Simulator(scene, ring).ping(scene.sensor_pose, noise=Noise(tof=1e-6), rng=np.random.default_rng(1))
    paths = ping.tof * ping.speed_of_sound
    flood = 5000
    flooded_group = np.full(flood, 30)
    flooded_paths = np.random.default_rng(2).uniform(0.5, 5.0, (flood, 2))
    together = classify.ring_consistency(ring, np.concatenate([ping.group, flooded_group]),
                                         np.concatenate([paths, flooded_paths]), SIGMA_PATH)
    alone = classify.ring_consistency(ring, ping.group, paths, SIGMA_PATH)
    assert_array_equal(together.cls[ping.n_echoes:], UNKNOWN)
    assert np.isnan(together.chi2_edge[ping.n_echoes:]).all()
    # echoes of groups out of reach of group 30 are tested exactly as without the flood
    others = ~np.isin(ping.group, [28, 29, 30, 31, 32])
    assert np.count_nonzero(others) > 20
    assert_array_equal(together.cls[:ping.n_echoes][others], alone.cls[others])
    assert_allclose(together.chi2_edge[:ping.n_echoes][others], alone.chi2_edge[others], rtol=1e-9)


# --------------------------------------------------------------------------- bad input

def test_error_handling():
    # Bad arguments raise ValueError naming the argument ...
    for sigma in (0.0, -0.01, np.nan, [0.02, 0.0]):
        with pytest.raises(ValueError, match="sigma"):
            amplitude_rule(1.0, 0.5, 0.5, 1.0, sigma)
    with pytest.raises(ValueError, match="shape"):
        classify_amplitudes(np.ones((3, 4)), 0.02)
    with pytest.raises(ValueError, match="theta0"):
        working_range(0.08, math.radians(95), SIGMA_REL)
    with pytest.raises(ValueError, match="sigma_rel"):
        separation_limits(1.0, THETA0, 0.2)  # 6 sigma above A_max: no separation can work
    with pytest.raises(ValueError, match="margin_rule"):
        working_range(0.08, THETA0, SIGMA_REL, margin_rule="guess")
    with pytest.raises(ValueError, match="separation"):
        plane_inclination(1.0, 1.0, 0.0)
    with pytest.raises(ValueError, match="separations"):
        choose_pair([0.04, -0.12], 1.0, THETA0, SIGMA_REL)
    receivers = np.zeros((2, 3, 2))
    with pytest.raises(ValueError, match="receivers"):
        geometric_consistency(np.zeros(2), np.zeros((2, 3)), np.ones((2, 3)), SIGMA_PATH)
    with pytest.raises(ValueError, match="paths"):
        geometric_consistency(np.zeros(2), receivers, np.ones((2, 4)), SIGMA_PATH)
    with pytest.raises(ValueError, match="transmitter"):
        geometric_consistency(np.zeros(3), receivers, np.ones((2, 3)), SIGMA_PATH)
    with pytest.raises(ValueError, match="sigma_path"):
        geometric_consistency(np.zeros(2), receivers, np.ones((2, 3)), 0.0)
    with pytest.raises(ValueError, match="z must"):
        geometric_consistency(np.zeros(2), receivers, np.ones((2, 3)), SIGMA_PATH, z=0.0)
    with pytest.raises(ValueError, match="one emitter"):
        classify.ring_consistency(load_layout("barshan_kuc_pair"), [0], np.ones((1, 2)), SIGMA_PATH)
    ring_layout = load_layout("browne_ring")
    for group in (48, -1):
        with pytest.raises(ValueError, match=rf"group indices must be in \[0, 48\), got {group} in row 1"):
            classify.ring_consistency(ring_layout, [0, group], np.ones((2, 2)), SIGMA_PATH)
    for sigma_path in (np.nan, -SIGMA_PATH, "wide", [SIGMA_PATH, SIGMA_PATH]):
        with pytest.raises(ValueError, match="sigma_path must be a finite number > 0"):
            classify.ring_consistency(ring_layout, [0], np.ones((1, 2)), sigma_path)
    with pytest.raises(ValueError, match="paths"):
        classify.ring_consistency(ring_layout, [0], np.ones((1, 3)), SIGMA_PATH)
    for z in (0.0, np.nan, [3.5, 3.5], "3.5", None, np.array("3.5"), 3.5j):
        with pytest.raises(ValueError, match="z must"):
            classify.ring_consistency(ring_layout, [0], np.ones((1, 2)), SIGMA_PATH, z=z)

    # ... bad data values give UNKNOWN / NaN / zero weight, never an exception.
    result = classify_amplitudes([[[np.nan, 0.5], [0.5, 1.0]], [[np.inf, 0.5], [0.5, 1.0]]], 0.02)
    assert_array_equal(result.cls, UNKNOWN)
    assert_array_equal(result.confidence, 0.0)
    assert_array_equal(result.margin, 0.0)
    assert np.all(np.isnan(working_range([np.nan, -0.08, 0.0], THETA0, SIGMA_REL)))
    assert np.all(np.isnan(separation_limits([np.inf, -1.0], THETA0, SIGMA_REL)))
    assert_array_equal(choose_pair([0.04, 0.12], [np.nan, 0.0], THETA0, SIGMA_REL), [-1, -1])
    assert np.isnan(plane_inclination(1.0, 1.1, 0.08))  # |R_bb' - R_aa'| > d
    assert np.isnan(corner_inclination(np.nan, 1.0, 1.0, 0.08))
    assert np.isnan(inclination_variance(0.08, 1e-3, 0.0, EDGE))
    assert_allclose(fusion_weights([np.nan, 0.0, -1.0, 4.0]), [0, 0, 0, 1])
    assert_array_equal(fusion_weights([[np.nan, np.inf]]), [[0.0, 0.0]])
    fused, variance = fuse([[np.nan, 1.0], [np.nan, np.nan]], [[1.0, 4.0], [1.0, 1.0]])
    assert_allclose(fused, [1.0, np.nan])
    assert_allclose(variance, [4.0, np.nan])

    ring = ring_receivers((0, 1))
    paths = exact_paths(EDGE, ring, 0.5, np.radians([1.0, 2.0, 3.0, 4.0]))
    paths[0, 1:] = np.nan  # one receiver left: nothing to test
    paths[1, :2] = np.nan  # two receivers: no redundancy
    paths[2, 0] = -1.0  # a negative path is dropped; three receivers remain
    transmitter = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [np.nan, 0.0]])
    with np.errstate(all="raise"):
        result = geometric_consistency(transmitter, np.broadcast_to(ring, (4, 4, 2)), paths, SIGMA_PATH)
    assert_array_equal(result.cls, [UNKNOWN, UNKNOWN, EDGE, UNKNOWN])
    assert_array_equal(result.dof, [-1, 0, 1, -2])
    assert_array_equal(result.confidence[[0, 1, 3]], 0.0)
    assert np.all(np.isnan(result.chi2_edge[[0, 1, 3]])) and np.all(np.isnan(result.virtual_image[[0, 1, 3]]))
    # A ring ping with missing receivers, a path shorter than the height offset and no echoes at all.
    paths = np.array([[np.nan, np.nan], [0.05, 2.0], [2.0, np.inf]])
    with np.errstate(all="raise"):
        result = classify.ring_consistency(ring_layout, [0, 1, 2], paths, SIGMA_PATH)
        empty = classify.ring_consistency(ring_layout, np.zeros(0, int), np.zeros((0, 2)), SIGMA_PATH)
    assert_array_equal(result.cls, UNKNOWN)
    assert_array_equal(result.confidence, 0.0)
    assert empty.cls.shape == (0,) and empty.virtual_image.shape == (0, 2)
