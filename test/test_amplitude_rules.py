"""Barshan & Kuc's pairs (sonar_ring.amplitude_rules): the paper's numbers, the amplitude rules on the
analytic curves, eq 41 fusion and the inclination."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal

from sonar_ring import amplitude_rules, localise
from sonar_ring.amplitude_rules import (
    amplitude_rule,
    choose_pair,
    classify_amplitudes,
    corner_inclination,
    fuse,
    fusion_weights,
    inclination_variance,
    plane_inclination,
    separation_limits,
    working_range,
)
from sonar_ring.geometry import beam_half_angle, load_layout
from sonar_ring.landmarks import CORNER, EDGE, PLANE, UNKNOWN

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
    for rule in amplitude_rules.MARGIN_RULES:
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


# --------------------------------------------------------------------------- bad input

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
