"""Phase-shift azimuth (Kreczmer 2017): eqs 1-8, the §6.2 robustness procedure and Table 1, §7's wall test.

Constants are the paper's: 40 kHz, lambda = 8.7 mm, hence c = 348 m/s and T = 25 us;
timer tick 0.33 us.
"""

import math

import mpmath
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal

from sonar_ring import doa
from sonar_ring.doa import Reason
from sonar_ring.geometry import load_layout

WAVELENGTH = 8.7e-3
SPEED = 348.0
PERIOD = WAVELENGTH / SPEED
TIMER = 0.33e-6
MM = 1e-3
US = 1e-6


def triad(b1, b2):
    """Receivers R0, R1, R2 (x, y) of a module facing +x, R0 left-most at y = 0."""
    return np.array([[0.0, 0.0], [0.0, -b1], [0.0, -(b1 + b2)]])


def exact_delays(angle, b1, b2):
    """Unwrapped plane-wave delays of eq 4 with n = 0: b sin(phi) / c."""
    sine = np.sin(angle)
    return b1 * sine / SPEED, (b1 + b2) * sine / SPEED


# --------------------------------------------------------------------------- conventions

def test_shipped_layout_matches_kreczmer_sign_convention():
    layout = load_layout("kreczmer_triad")
    receivers = layout.group_receivers()[0, :, :2]
    assert_allclose(np.linalg.norm(np.diff(receivers, axis=0), axis=1), [11 * MM, 4 * MM], atol=1e-12)
    assert receivers[0, 1] > receivers[2, 1]  # R0 is the left (+y) end
    # A source ahead-left (phi = +30 deg, CCW) reaches R0 first: both delays are the
    # small positive b sin(phi) / c of eq 1 (b1 sin 30 = 5.5 mm < lambda, no wrap).
    middle = receivers[[0, 2]].mean(axis=0)  # far field: direction seen from the R0 -- R2 midpoint
    source = middle + 5.0 * np.array([math.cos(math.radians(30)), math.sin(math.radians(30))])
    t01, t02 = doa.phase_delays(source, receivers, WAVELENGTH, SPEED, far_field=True)
    assert_allclose([t01, t02], np.array([11, 15]) * MM * 0.5 / SPEED, rtol=1e-12)
    result = doa.azimuth(t01, t02, 11 * MM, 4 * MM, WAVELENGTH, SPEED, 0.08, math.radians(50))
    assert result.valid and result.reason == Reason.OK
    assert_allclose(result.angle, math.radians(30), atol=1e-12)


# --------------------------------------------------------------------------- azimuth (eqs 1-6)

@pytest.mark.parametrize("b1, b2, eps", [(11 * MM, 4 * MM, 0.08), (11 * MM, 15 * MM, 0.05), (4 * MM, 11 * MM, 0.3)])
def test_azimuth_inverts_exact_delays_wrapped_or_not(b1, b2, eps):
    angle = np.radians(np.linspace(-60, 60, 241))
    t01, t02 = exact_delays(angle, b1, b2)
    wrapped = doa.azimuth(np.mod(t01, PERIOD), np.mod(t02, PERIOD), b1, b2, WAVELENGTH, SPEED, eps, math.radians(61))
    shifted = doa.azimuth(t01 - 3 * PERIOD, t02 + 7 * PERIOD, b1, b2, WAVELENGTH, SPEED, eps, math.radians(61))
    assert wrapped.valid.all() and shifted.valid.all()
    assert_array_equal(wrapped.candidates, 1)
    assert_allclose(wrapped.angle, angle, atol=1e-12)
    assert_allclose(shifted.angle, angle, atol=1e-12)
    # eq 4: n_k lambda = c t_0k - b sin(phi) with the wrapped delays.
    assert_allclose(wrapped.n1 * WAVELENGTH, SPEED * np.mod(t01, PERIOD) - b1 * np.sin(angle), atol=1e-12)
    assert_allclose(wrapped.n2 * WAVELENGTH, SPEED * np.mod(t02, PERIOD) - (b1 + b2) * np.sin(angle), atol=1e-12)


def test_azimuth_is_vectorised_over_any_shape():
    angle = np.radians(np.arange(-45, 46, 5.0)).reshape(1, 19)
    t01, t02 = exact_delays(angle, 11 * MM, 4 * MM)
    result = doa.azimuth(t01, t02.T, 11 * MM, 4 * MM, WAVELENGTH, SPEED, 0.08, math.radians(50))
    assert result.angle.shape == (19, 19)
    # Only the diagonal holds consistent (t01, t02) pairs.
    assert_allclose(np.diag(result.angle), angle[0], atol=1e-12)
    assert np.diag(result.valid).all()


ROBUST_11_4 = doa.robustness(11 * MM, 4 * MM, math.radians(50), WAVELENGTH, SPEED)


@settings(max_examples=300, deadline=None)
@given(angle_deg=st.floats(-50, 50),
       error1=st.floats(-1, 1) | st.sampled_from([-1.0, 1.0]),
       error2=st.floats(-1, 1) | st.sampled_from([-1.0, 1.0]))
def test_errors_within_the_robust_delay_error_never_mislead(angle_deg, error1, error2):
    """§6.2's guarantee: any errors in [-dt, dt] keep the solution unique and correct."""
    angle = math.radians(angle_deg)
    dt = ROBUST_11_4.delay_error
    t01, t02 = exact_delays(angle, 11 * MM, 4 * MM)
    result = doa.azimuth(np.mod(t01 + error1 * dt, PERIOD), np.mod(t02 + error2 * dt, PERIOD), 11 * MM, 4 * MM,
                         WAVELENGTH, SPEED, ROBUST_11_4.eps, math.radians(60))
    assert result.valid and result.candidates == 1
    # Worst case of the fused sine a1 u1 + a2 u2: |a1| c dt / b1 + |a2| c dt / b12, with the
    # GLS weights for delay correlation 1/2: a1 = b1 (b1 - b12 / 2) / (b1^2 + b12^2 - b1 b12).
    b1, b12 = 11.0, 15.0
    a1 = b1 * (b1 - b12 / 2) / (b1**2 + b12**2 - b1 * b12)
    sine_bound = SPEED * dt * (abs(a1) / (b1 * MM) + abs(1 - a1) / (b12 * MM))
    assert abs(math.sin(result.angle) - math.sin(angle)) <= sine_bound * (1 + 1e-9)


def test_too_large_errors_are_flagged_ambiguous_or_no_solution():
    b1, b2 = 11 * MM, 4 * MM
    t01, t02 = exact_delays(math.radians(50), b1, b2)
    # Past the robust 1.4 us: errors (-1.5, +1.5) us make the pair (n1, n2) + (2, 3)
    # mismatch by lambda (3/b12 - 2/b1) - 0.0815 = 0.0767 < eps = 0.09 (the eps 1.5 us needs).
    result = doa.azimuth(t01 - 1.5 * US, t02 + 1.5 * US, b1, b2, WAVELENGTH, SPEED, 0.09, math.radians(50))
    assert result.reason == Reason.AMBIGUOUS and result.candidates == 2 and not result.valid
    assert np.isfinite(result.angle)  # the best-agreeing candidate, for diagnostics
    # At 0 deg, errors (+2, -2) us give the correct pair a mismatch 0.110 > eps = 0.08,
    # and every other pair is further than eps.
    t01, t02 = exact_delays(0.0, b1, b2)
    result = doa.azimuth(t01 + 2 * US, t02 - 2 * US, b1, b2, WAVELENGTH, SPEED, 0.08, math.radians(50))
    assert result.reason == Reason.NO_SOLUTION and result.candidates == 0
    assert np.isnan(result.angle) and not result.valid


def test_out_of_range_and_not_finite():
    b1, b2 = 11 * MM, 4 * MM
    t01, t02 = exact_delays(np.radians([55.0, -55.0, 49.0]), b1, b2)
    result = doa.azimuth(t01, t02, b1, b2, WAVELENGTH, SPEED, 0.08, math.radians(50))
    assert_array_equal(result.reason, [Reason.OUT_OF_RANGE, Reason.OUT_OF_RANGE, Reason.OK])
    assert_allclose(result.angle, np.radians([55.0, -55.0, 49.0]), atol=1e-12)
    result = doa.azimuth([np.nan, np.inf, 0.0], [0.0, 0.0, -np.inf], b1, b2, WAVELENGTH, SPEED, 0.08, 1.0)
    assert_array_equal(result.reason, Reason.NOT_FINITE)
    assert not result.valid.any() and np.isnan(result.angle).all()


# --------------------------------------------------------------------------- error models (eqs 7-8, timer)

def test_plane_wave_error_eq7():
    distance = np.array([0.1, 0.5, 1.5, 100.0])
    baseline = 11 * MM
    with mpmath.workdps(50):  # the literal sqrt(d^2 + b^2) - d, without cancellation trouble
        reference = [float(mpmath.sqrt(mpmath.mpf(d) ** 2 + mpmath.mpf(baseline) ** 2) - d) for d in distance]
    assert_allclose(doa.plane_wave_error(distance, baseline), reference, rtol=1e-15)
    assert_allclose(doa.plane_wave_error(100.0, baseline), baseline**2 / 200.0, rtol=1e-7)  # b^2 / (2 d)
    # Eq 7 is what the near-field model adds for a source broadside of R0 (Fig. 10).
    t01, = doa.phase_delays([1.5, 0.0], triad(baseline, 1.0)[:2], WAVELENGTH, SPEED)
    assert_allclose(t01 * SPEED, doa.plane_wave_error(1.5, baseline), rtol=1e-9)
    # "1 mm is equal to about 2.92 us" (§5.1) holds for c = 342.5 m/s.
    assert_allclose(1 * MM / 342.5, 2.92 * US, rtol=1e-3)


def test_angle_error_eq8_is_the_derivative_of_eq1():
    angle = np.radians([0.0, 20.0, 40.0, 60.0])
    baseline, dt = 4 * MM, 1 * US
    step = 1e-12
    derivative = (np.arcsin(np.sin(angle) + SPEED * step / baseline) - angle) / step
    assert_allclose(doa.angle_error(angle, baseline, SPEED, dt), derivative * dt, rtol=1e-6)
    # Fig. 13: 1 us on 4 mm at 0 deg is about 5 deg.
    assert_allclose(math.degrees(doa.angle_error(0.0, 4 * MM, SPEED, 1 * US)), 4.98, atol=0.01)


def test_timing_error_budget_adds_three_sigma_timer_and_plane_wave():
    assert_allclose(doa.timing_error_budget(0.3 * US, TIMER, 0.1 * US), 1.33 * US, rtol=1e-12)
    assert_allclose(doa.delay_std(0.2 * US, TIMER), math.sqrt(2 * 0.04 + 0.33**2 / 6) * US, rtol=1e-12)


def test_simulated_delay_noise_matches_delay_std_and_correlation():
    rng = np.random.default_rng(7)
    n = 40000
    angle = rng.uniform(-0.8, 0.8, n)
    source = 3.0 * np.stack([np.cos(angle), np.sin(angle)], axis=-1)
    receivers = triad(11 * MM, 4 * MM)
    exact = doa.phase_delays(source, receivers, WAVELENGTH, SPEED)
    noisy = doa.phase_delays(source, receivers, WAVELENGTH, SPEED, crossing_std=0.2 * US, timer_resolution=TIMER,
                             rng=rng)
    # Reduce the difference to (-T/2, T/2]: a crossing pushed past R0's wraps by T.
    error = np.mod(noisy - exact + PERIOD / 2, PERIOD) - PERIOD / 2
    assert (exact >= 0).all() and (exact < PERIOD).all()
    assert (noisy >= 0).all() and (noisy < PERIOD + TIMER).all()
    # Sampling error of a std from 40 000 draws is 0.35 %; of a correlation, 0.005.
    assert_allclose(error.mean(axis=0), 0.0, atol=0.01 * US)  # the random clock phase makes the timer unbiased
    assert_allclose(error.std(axis=0), doa.delay_std(0.2 * US, TIMER), rtol=0.02)
    assert_allclose(np.corrcoef(error.T)[0, 1], 0.5, atol=0.02)


def test_near_field_tends_to_far_field():
    receivers = triad(11 * MM, 4 * MM)
    direction = np.array([math.cos(0.6), math.sin(0.6)])
    origin = receivers[[0, 2]].mean(axis=0)
    for distance in (0.5, 2.0, 8.0):
        near = doa.phase_delays(origin + distance * direction, receivers, WAVELENGTH, SPEED)
        far = doa.phase_delays(origin + distance * direction, receivers, WAVELENGTH, SPEED, far_field=True)
        # Curvature: at most b^2 / (2 d) of path (eq 7), b = 11 mm off the origin.
        assert_allclose(near, far, atol=(11 * MM) ** 2 / (2 * distance) / SPEED)
        assert not np.allclose(near, far, atol=1e-3 * (11 * MM) ** 2 / (2 * distance) / SPEED)


# --------------------------------------------------------------------------- robustness (§6.2, Table 1)

# Table 1 of the paper and ours (lambda = 8.7 mm, c = 348 m/s; steps 0.1 us and 0.01 as the paper's precision).
# columns: b1, b2 (mm), range (deg); paper eps, dt (us), "min delta phi" (deg); our eps, dt (us)
TABLE_1 = [
    (11, 15, 50, 0.05, 0.9, 1.2, 0.05, 0.9),
    (11, 4, 50, 0.08, 1.4, 2.2, 0.08, 1.4),
    (4, 11, 60, 0.4, 1.5, 4.7, 0.17, 1.5),
    (4, 11, 50, 0.3, 2.5, 7.8, 0.29, 2.6),
]


@pytest.mark.parametrize("b1, b2, half_range, paper_eps, paper_dt, paper_min_error, our_eps, our_dt", TABLE_1)
def test_table_1_recomputed(b1, b2, half_range, paper_eps, paper_dt, paper_min_error, our_eps, our_dt):
    result = doa.robustness(b1 * MM, b2 * MM, math.radians(half_range), WAVELENGTH, SPEED)
    assert_allclose([result.eps, result.delay_error], [our_eps, our_dt * US], rtol=1e-9)
    # Against the paper: dt within one step (0.1 us); eps within one step (0.01) except at
    # (4, 11) +-60 deg, where the paper's 0.4 is an artefact of its loop (next test).
    assert abs(result.delay_error - paper_dt * US) <= 0.1 * US + 1e-12
    if half_range == 50:
        assert abs(result.eps - paper_eps) <= 0.01 + 1e-12
    # "min delta phi" is eq 8 at 0 deg averaged over the two pairs, i.e. the error of the
    # mean of eq 4's two arcsines, at the paper's dt; to the table's 0.1 deg rounding
    # plus 0.05 deg for the paper's unstated speed of sound.
    mean_error = 0.5 * (doa.angle_error(0.0, b1 * MM, SPEED, paper_dt * US)
                        + doa.angle_error(0.0, (b1 + b2) * MM, SPEED, paper_dt * US))
    assert_allclose(math.degrees(mean_error), paper_min_error, atol=0.1)
    # Our fused (GLS) estimate is better than the mean at 0 deg.
    assert result.angle_error_centre < 0.5 * (doa.angle_error(0.0, b1 * MM, SPEED, result.delay_error)
                                              + doa.angle_error(0.0, (b1 + b2) * MM, SPEED, result.delay_error))


@pytest.mark.parametrize("b1, b2, half_range", [row[:3] for row in TABLE_1])
def test_robustness_agrees_with_azimuth(b1, b2, half_range):
    """The two implement eq 6 independently: at dt all errors pass, one step further some fail."""
    b1, b2, max_angle = b1 * MM, b2 * MM, math.radians(half_range)
    result = doa.robustness(b1, b2, max_angle, WAVELENGTH, SPEED)
    angle, error1, error2 = np.meshgrid(np.linspace(-max_angle, max_angle, 1001), np.linspace(-1, 1, 9),
                                        np.linspace(-1, 1, 9), indexing="ij")
    exact1, exact2 = exact_delays(angle, b1, b2)

    def right_and_unique(dt, eps):
        found = doa.azimuth(exact1 + error1 * dt, exact2 + error2 * dt, b1, b2, WAVELENGTH, SPEED, eps, math.pi / 2)
        return (found.candidates == 1) & (np.abs(np.sin(found.angle) - np.sin(angle)) < 0.1)

    assert right_and_unique(result.delay_error, result.eps).all()
    next_dt = result.delay_error + 0.1 * US
    next_eps = 0.01 * (math.floor(SPEED * next_dt * (1 / b1 + 1 / (b1 + b2)) / 0.01) + 1)
    assert not right_and_unique(next_dt, next_eps).all()


def test_paper_eps_at_60_deg_comes_from_raising_eps_after_the_arcsine_left_its_domain():
    # At dt = 1.6 us the correct u1 = sin 60 + c dt / 4 mm exceeds 1 at the edge: no eps finds it.
    assert math.sin(math.radians(60)) + SPEED * 1.6 * US / (4 * MM) > 1
    # The paper's loop raises eps anyway until the nearest wrong pair (k2 = +-1, mismatch
    # lambda / 15 mm minus the correct mismatch) passes, then reports the previous eps.
    correct_mismatch = SPEED * 1.6 * US * (1 / (4 * MM) + 1 / (15 * MM))
    first_wrong_eps = WAVELENGTH / (15 * MM) - correct_mismatch
    assert_allclose(math.floor(first_wrong_eps / 0.01) * 0.01, 0.4, atol=1e-9)


@pytest.mark.parametrize("b1, b2, half_range, exact_limit", [
    # A wrong pair (k1, k2) is lambda |k1/b1 - k2/b12| from the correct one, and dt costs
    # c dt (1/b1 + 1/b12) of mismatch on each, so dt* = that distance / (2 c (1/b1 + 1/b12)):
    (11, 15, 50, 3 * PERIOD / 74),  # (2, 5): the wrong candidate sits beyond -52 deg
    (11, 4, 50, 3 * PERIOD / 52),  # (2, 3)
    (4, 11, 50, 4 * PERIOD / 38),  # (0, 1)
    # ... unless the correct arcsine leaves [-1, 1] first: sin(60) + c dt / b1 = 1.
    (4, 11, 60, (1 - math.sin(math.radians(60))) * 4 * MM / SPEED),
])
def test_robustness_converges_to_the_exact_limit(b1, b2, half_range, exact_limit):
    result = doa.robustness(b1 * MM, b2 * MM, math.radians(half_range), WAVELENGTH, SPEED,
                            delay_step=0.005 * US, eps_step=1e-5)
    assert exact_limit - 0.005 * US - 1e-12 <= result.delay_error <= exact_limit
    assert_allclose(result.eps, SPEED * result.delay_error * (1 / (b1 * MM) + 1 / ((b1 + b2) * MM)), atol=1e-5)


def test_robustness_of_an_aliasing_layout_is_zero():
    # b1 + b2 = 3 b1 / 2 with b1 = 2 lambda: k = (3, 2) shifts both sines by 1.5 -- an exact alias.
    result = doa.robustness(2 * WAVELENGTH, WAVELENGTH, math.radians(60), WAVELENGTH, SPEED)
    assert result == doa.Robustness(0.0, 0.0, 0.0, 0.0)


# --------------------------------------------------------------------------- §7: the wall experiment

def wall_experiment(layout, distances, rotations_deg, trials, rng, *, crossing_std, timer, tof_std=0.0):
    """Kreczmer §7: the module, rotated by alpha about its middle, faces a wall at each distance.

    Returns the expected azimuth (eq 9: phi = -alpha), phase delays (N, 2), TOFs (N, 3),
    wall distance and the wall's normal angle in the module frame, for
    N = len(distances) * len(rotations) * trials echoes.
    """
    receivers = layout.group_receivers()[0]  # (3, 3)
    emitter = layout.transmitters[layout.group_transmitters[0, 0]]  # (3,)
    middle = 0.5 * (receivers[0] + receivers[2])
    distance, alpha, _ = np.meshgrid(distances, np.radians(rotations_deg), np.arange(trials), indexing="ij")
    distance, alpha = distance.ravel(), alpha.ravel()
    normal_angle = -alpha  # the wall's normal, seen from the rotated module
    plane_offset = distance + np.cos(normal_angle) * middle[0] + np.sin(normal_angle) * middle[1]
    image = doa.wall_image(emitter, plane_offset, normal_angle)  # (N, 3)
    delays = doa.phase_delays(image[:, :2], receivers[:, :2], WAVELENGTH, SPEED, crossing_std=crossing_std,
                              timer_resolution=timer, rng=rng)
    tofs = np.linalg.norm(image[:, None, :] - receivers, axis=-1) / SPEED
    tofs = tofs + rng.normal(0.0, tof_std, tofs.shape)
    return -alpha, delays, tofs, plane_offset, normal_angle


# Timing noise as in §7: the timer's 0.33 us tick and a zero-crossing jitter of 0.2 us,
# chosen so that the paper's own error budget (3 sigma + tick) stays inside the 1.4 us
# that Table 1 certifies for this layout; the paper gives no sigma for the phase timing.
CROSSING_STD = 0.2 * US


def test_wall_experiment_monte_carlo():
    layout = load_layout("kreczmer_triad")
    receivers = layout.group_receivers()[0, :, :2]
    b1, b2 = np.linalg.norm(np.diff(receivers, axis=0), axis=1)
    assert doa.timing_error_budget(doa.delay_std(CROSSING_STD, TIMER), TIMER) <= ROBUST_11_4.delay_error
    rotations = np.arange(-50, 51, 5)
    trials = 400
    expected, delays, _, _, _ = wall_experiment(layout, [1.0, 1.5, 2.0], rotations, trials, np.random.default_rng(3),
                                                crossing_std=CROSSING_STD, timer=TIMER)
    result = doa.azimuth(delays[:, 0], delays[:, 1], b1, b2, WAVELENGTH, SPEED, ROBUST_11_4.eps,
                         layout.beam_half_angle)
    # Per rotation, pooling the three distances (they differ by < 0.01 deg of curvature bias).
    shape = (3, rotations.size, trials)
    unique = (result.candidates == 1).reshape(shape).transpose(1, 0, 2).reshape(rotations.size, -1)
    error = (result.angle - expected).reshape(shape).transpose(1, 0, 2).reshape(rotations.size, -1)
    assert unique.all() and result.valid.all()
    assert np.abs(error).max() < math.radians(3)  # no wrong (n1, n2): those are off by >= 15 deg
    three_sigma = 3 * error.std(axis=1)
    central = np.abs(rotations) <= 20
    assert (three_sigma[central] < math.radians(2)).all()  # the paper's "3 sigma below 2 deg"
    # And the spread is what the first-order model predicts (1200 draws: 2 % sampling error).
    predicted = doa.azimuth_std(np.radians(-rotations), b1, b2, SPEED, doa.delay_std(CROSSING_STD, TIMER))
    assert_allclose(error.std(axis=1), predicted, rtol=0.1)
    assert_allclose(error.mean(axis=1), 0.0, atol=0.05 * predicted.max() + math.radians(0.02))


# --------------------------------------------------------------------------- landmark

def test_triad_landmark_of_a_wall_echo_is_the_reflection_point():
    layout = load_layout("kreczmer_triad")
    receivers = layout.group_receivers()[0]
    emitter = layout.transmitters[0]
    height = emitter[2] - receivers[0, 2]
    rotations = np.arange(-50, 51, 10)
    expected, delays, tofs, offset, normal_angle = wall_experiment(layout, [1.0, 2.0], rotations, 1,
                                                                   np.random.default_rng(0), crossing_std=0.0,
                                                                   timer=0.0)
    landmark = doa.triad_landmark(receivers[:, :2], emitter[:2], tofs, delays[:, 0], delays[:, 1], WAVELENGTH, SPEED,
                                  0.08, math.radians(60), delay_std=0.3 * US, tof_std=10 * US, height_offset=height)
    assert landmark.valid.all()
    # Near-field parallax only: the R0 -- R1 pair's midpoint is 2 mm from the triad's origin,
    # which tilts its arcsine by 2 mm cos(phi) / (2 d) at the image 2 d away; its GLS weight is 0.21.
    assert_allclose(landmark.azimuth, expected, atol=0.22 * 2 * MM / 2.0)
    # The reflection point: on the wall, straight ahead of the module's middle (the emitter's x-y).
    normal = np.stack([np.cos(normal_angle), np.sin(normal_angle)], axis=-1)
    middle = receivers[[0, 2], :2].mean(axis=0)
    # Range: the mean of R0's and R2's paths is the path to the middle within (7.5 mm)^2 / 2 d.
    assert_allclose(np.sum(landmark.position * normal, axis=-1), offset, atol=2e-5)
    assert_allclose(landmark.position, middle + (offset - normal @ middle)[:, None] * normal,
                    atol=2e-5 + 0.22 * 2 * MM / 2.0 * 1.0)  # plus the parallax above, times 1 m of range
    assert_allclose(landmark.range, np.linalg.norm(landmark.position - middle, axis=-1), rtol=1e-12)


def test_triad_landmark_of_an_edge_and_its_covariance():
    # Emitter 6 mm ahead of the receivers' middle, edge at 1.2 m, 25 deg left of a module facing 30 deg.
    yaw = math.radians(30)
    rotation = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    receivers = triad(11 * MM, 4 * MM) @ rotation.T + [0.1, 0.05]
    middle = receivers[[0, 2]].mean(axis=0)
    emitter = middle + rotation @ [6 * MM, 0.0]
    edge = middle + 1.2 * np.array([math.cos(yaw + math.radians(25)), math.sin(yaw + math.radians(25))])
    path = np.linalg.norm(edge - emitter) + np.linalg.norm(edge - receivers, axis=-1)
    delays = doa.phase_delays(edge, receivers, WAVELENGTH, SPEED)
    exact = doa.triad_landmark(receivers, emitter, path / SPEED, delays[0], delays[1], WAVELENGTH, SPEED, 0.08,
                               math.radians(60), delay_std=0.3 * US, tof_std=5 * US)
    assert exact.valid
    # Near-field parallax of the R0 -- R1 pair (see the wall test): 0.21 * 2 mm cos(25 deg) / 1.2 m.
    parallax = 0.22 * 2 * MM * math.cos(math.radians(25)) / 1.2
    assert_allclose(exact.bearing, yaw + math.radians(25), atol=parallax)
    assert_allclose(exact.position, edge, atol=1.2 * parallax + 2e-5)

    rng = np.random.default_rng(11)
    n = 20000
    crossing_std, tof_std = 0.25 * US, 5 * US
    noisy_delays = doa.phase_delays(np.broadcast_to(edge, (n, 2)), receivers, WAVELENGTH, SPEED,
                                    crossing_std=crossing_std, timer_resolution=TIMER, rng=rng)
    noisy_tofs = path / SPEED + rng.normal(0.0, tof_std, (n, 3))
    noisy = doa.triad_landmark(receivers, emitter, noisy_tofs, noisy_delays[:, 0], noisy_delays[:, 1], WAVELENGTH,
                               SPEED, 0.08, math.radians(60), delay_std=doa.delay_std(crossing_std, TIMER),
                               tof_std=tof_std)
    assert noisy.valid.all()
    assert not np.isnan(noisy.position).any() and not np.isnan(noisy.covariance).any()
    sample = np.cov(noisy.position.T)
    # First order is exact to < 1 % here; 20 000 draws estimate a variance to 1 %.
    assert_allclose(np.linalg.eigvalsh(sample), np.linalg.eigvalsh(noisy.covariance.mean(axis=0)), rtol=0.05)
    assert_allclose(sample, noisy.covariance[0], rtol=0.05, atol=0.02 * np.abs(sample).max())


def test_triad_landmark_flags_invalid_echoes():
    receivers = triad(11 * MM, 4 * MM)
    emitter = receivers[[0, 2]].mean(axis=0) + [0.0, 0.1]  # 10 cm off: short paths cannot reach
    t01, t02 = exact_delays(np.radians([10.0, 10.0, 10.0, 10.0, 70.0]), 11 * MM, 4 * MM)
    tofs = np.array([1.0, 0.05, -1.0, np.nan, 1.0])[:, None] * [1, 1, 1] / SPEED
    landmark = doa.triad_landmark(receivers, emitter, tofs, t01, t02, WAVELENGTH, SPEED, 0.08, math.radians(60),
                                  delay_std=0.3 * US, tof_std=5 * US)
    assert_array_equal(landmark.reason,
                       [Reason.OK, Reason.BAD_RANGE, Reason.BAD_RANGE, Reason.NOT_FINITE, Reason.OUT_OF_RANGE])
    assert_array_equal(landmark.valid, [True, False, False, False, False])
    assert np.isfinite(landmark.position[0]).all() and np.isnan(landmark.position[1:]).all()
    assert np.isfinite(landmark.covariance[0]).all() and np.isnan(landmark.covariance[1:]).all()


# --------------------------------------------------------------------------- arguments

def test_error_handling():
    good = dict(b1=11 * MM, b2=4 * MM, wavelength=WAVELENGTH, speed_of_sound=SPEED)
    with pytest.raises(ValueError, match="b1 == b2"):
        doa.azimuth(0.0, 0.0, 5 * MM, 5 * MM, WAVELENGTH, SPEED, 0.1, 1.0)
    for name, value in [("b1", 0.0), ("b2", -1.0), ("wavelength", 0.0), ("speed_of_sound", math.nan)]:
        with pytest.raises(ValueError, match=name):
            doa.azimuth(0.0, 0.0, **{**good, name: value}, eps=0.1, max_angle=1.0)
    with pytest.raises(ValueError, match="eps"):
        doa.azimuth(0.0, 0.0, **good, eps=0.0, max_angle=1.0)
    with pytest.raises(ValueError, match="max_angle"):
        doa.azimuth(0.0, 0.0, **good, eps=0.1, max_angle=2.0)
    with pytest.raises(ValueError, match="delay_correlation"):
        doa.azimuth(0.0, 0.0, **good, eps=0.1, max_angle=1.0, delay_correlation=1.0)
    with pytest.raises(ValueError, match="delay_step"):
        doa.robustness(max_angle=1.0, **good, delay_step=0.0)
    with pytest.raises(ValueError, match="crossing_std"):
        doa.phase_delays([1.0, 0.0], triad(11 * MM, 4 * MM), WAVELENGTH, SPEED, crossing_std=-1.0)
    with pytest.raises(ValueError, match="receivers_xy"):
        doa.phase_delays([1.0, 0.0], [0.0, 0.0], WAVELENGTH, SPEED)
    with pytest.raises(ValueError, match="collinear"):
        doa.triad_landmark([[0, 0], [0.001, -0.011], [0, -0.015]], [0, 0], [1e-3] * 3, 0.0, 0.0, WAVELENGTH, SPEED,
                           0.08, 1.0, delay_std=0.0, tof_std=0.0)
    with pytest.raises(ValueError, match="shape|need"):
        doa.triad_landmark(triad(11 * MM, 4 * MM)[:2], [0, 0], [1e-3] * 3, 0.0, 0.0, WAVELENGTH, SPEED, 0.08, 1.0,
                           delay_std=0.0, tof_std=0.0)
    # Bad data values are flags, not exceptions.
    assert doa.azimuth(np.nan, 0.0, **good, eps=0.1, max_angle=1.0).reason == Reason.NOT_FINITE
    assert np.isnan(doa.phase_delays([np.nan, 0.0], triad(11 * MM, 4 * MM), WAVELENGTH, SPEED)).all()
