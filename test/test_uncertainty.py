"""Uncertainty of the localisation (sonar_ring.uncertainty): Jacobians, covariances against Monte Carlo,
the Cramer-Rao bound, and bad input."""

import numpy as np
import pytest
from numpy.testing import assert_allclose
from test_localise import SIGMA_TOF, C, browne_pair, corner_paths, edge_paths, norm

from sonar_ring import localise as loc
from sonar_ring import uncertainty


@pytest.mark.parametrize("model,paths", [("corner", corner_paths), ("plane", corner_paths), ("edge", edge_paths)])
def test_position_jacobian_matches_finite_differences(model, paths):
    tx, rx1, rx2 = browne_pair()
    points = np.array([[0.5, 0.1], [2.3, -0.6], [5.0, 0.9]])
    d1, d2 = paths(tx, rx1, rx2, points)
    estimate = loc.MODELS[model](tx, rx1, rx2, d1, d2)
    jacobian = uncertainty.position_jacobian(estimate, tx, rx1, rx2)
    step = 1e-6
    for n in range(2):
        plus = [d1, d2]
        minus = [d1, d2]
        plus[n], minus[n] = plus[n] + step, minus[n] - step
        numeric = (loc.MODELS[model](tx, rx1, rx2, *plus).position - loc.MODELS[model](tx, rx1, rx2, *minus).position)
        assert_allclose(jacobian[..., n], numeric / (2 * step), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("model,paths", [("corner", corner_paths), ("edge", edge_paths)])
def test_covariance_matches_monte_carlo(model, paths):
    tx, rx1, rx2 = browne_pair()
    point = np.array([2.31, 0.5])
    d1, d2 = paths(tx, rx1, rx2, point)
    estimate = loc.MODELS[model](tx, rx1, rx2, d1, d2)
    sigma_speed = 0.5
    predicted = uncertainty.position_covariance(estimate, tx, rx1, rx2,
                                        uncertainty.path_covariance(d1, d2, SIGMA_TOF, C, sigma_speed))
    rng = np.random.default_rng(11)
    n = 20000
    speed_error = rng.normal(0, sigma_speed, n) / C
    noisy1 = d1 * (1 + speed_error) + C * SIGMA_TOF * rng.normal(size=n)
    noisy2 = d2 * (1 + speed_error) + C * SIGMA_TOF * rng.normal(size=n)
    sample = loc.MODELS[model](tx, rx1, rx2, noisy1, noisy2)
    assert sample.valid.all()
    observed = np.cov(sample.position.T)
    assert_allclose(np.sqrt(np.diag(observed)), np.sqrt(np.diag(predicted)), rtol=0.05)
    correlation = observed[0, 1] / np.sqrt(observed[0, 0] * observed[1, 1])
    assert_allclose(correlation, predicted[0, 1] / np.sqrt(predicted[0, 0] * predicted[1, 1]), atol=0.03)


def test_speed_of_sound_term_of_the_path_covariance():
    cov = uncertainty.path_covariance(2.0, 3.0, SIGMA_TOF, C, 1.0)
    independent = (C * SIGMA_TOF) ** 2
    assert_allclose(cov, independent * np.eye(2) + (1.0 / C) ** 2 * np.outer([2.0, 3.0], [2.0, 3.0]), rtol=1e-15)
    assert uncertainty.path_covariance(np.ones((4, 3)), 2.0, SIGMA_TOF, C).shape == (4, 3, 2, 2)


@pytest.mark.parametrize("phi_deg", [-45, -30, -15, 0, 15, 30, 45])
def test_monte_carlo_meets_the_cramer_rao_bound(phi_deg):
    """sigma_t = 1 us, D = 40 mm, transmitter at the pair's mid-point, corner at 2 m (cramer_rao_bound's formulas)."""
    tx, rx1, rx2 = np.zeros(2), np.array([0.0, 0.02]), np.array([0.0, -0.02])
    phi = np.radians(phi_deg)
    apex = 2.0 * np.array([np.cos(phi), np.sin(phi)])
    d1, d2 = corner_paths(tx, rx1, rx2, apex)
    true_bearing = np.arctan2(*(2 * apex - rx1)[::-1])  # eq 4 is the bearing of T' at R1
    rng = np.random.default_rng(phi_deg + 100)
    n = 20000
    noisy1 = d1 + C * SIGMA_TOF * rng.normal(size=n)
    noisy2 = d2 + C * SIGMA_TOF * rng.normal(size=n)
    sigma_bearing, sigma_range = uncertainty.cramer_rao_bound(0.04, SIGMA_TOF, C, true_bearing)
    bearings = loc.bearing(noisy1, noisy2, 0.04).value
    ranges = norm(loc.corner(tx, rx1, rx2, noisy1, noisy2).position - tx)
    assert abs(np.std(bearings) / sigma_bearing - 1) < 0.10
    assert abs(np.mean(bearings) - true_bearing) < 0.1 * sigma_bearing
    assert abs(np.std(ranges) / sigma_range - 1) < 0.10
    assert abs(np.mean(ranges) - 2.0) < 0.1 * sigma_range


def test_error_handling():
    tx, rx1, rx2 = browne_pair()
    with pytest.raises(ValueError, match="sigma_tof >= 0"):
        uncertainty.path_covariance(1.0, 1.0, -1e-6, C)
    with pytest.raises(ValueError, match="speed_of_sound > 0"):
        uncertainty.path_covariance(1.0, 1.0, 1e-6, 0.0)
    # numbers and arrays alike: NaN, infinity or one bad value anywhere is refused; nothing to check is no error
    for sigma_tof, speed, sigma_speed in ((np.nan, C, 0.0), (1e-6, np.inf, 0.0), (1e-6, C, -np.inf),
                                          (np.array([1e-6, np.nan]), C, 0.0), (1e-6, np.array([C, -C]), 0.0),
                                          (1e-6, C, np.array([0.0, np.inf])), (1e-6, np.float32(0.0), 0.0)):
        with pytest.raises(ValueError, match="path_covariance: need sigma_tof >= 0"):
            uncertainty.path_covariance(1.0, 1.0, sigma_tof, speed, sigma_speed)
    uncertainty.check_path_noise(np.empty(0), np.empty(0), np.empty(0), "empty")
    uncertainty.check_path_noise(0, 343, 0, "integers")
    with pytest.raises(ValueError, match=r"\(\.\.\., 2, 2\)"):
        uncertainty.position_covariance(loc.corner(tx, rx1, rx2, 1.0, 1.0), tx, rx1, rx2, np.eye(3))
    with pytest.raises(ValueError, match="unknown model"):
        uncertainty.position_jacobian(loc.PointEstimate(np.zeros(2), np.True_, np.int8(0), "blob"), tx, rx1, rx2)
