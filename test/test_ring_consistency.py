"""The single emitter's evidence (sonar_ring.ring_consistency): the consistency test on exact and noisy
ring geometry, the joining of overlapping groups, and bad input."""

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from sonar_ring import localise
from sonar_ring.geometry import load_layout
from sonar_ring.landmarks import CORNER, EDGE, PLANE, UNKNOWN
from sonar_ring.ring_consistency import (
    CHI2_3_SIGMA,
    CONSISTENCY_Z,
    SAG_BAND,
    _chi2_upper_quantile,
    geometric_consistency,
    overlapping_groups,
    ring_consistency,
)
from sonar_ring.simulate import Noise, Simulator, load_scene

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


def test_joint_fit_covariance_is_the_weighted_least_squares_one():
    # (J^T W J)^-1 from a numerical Jacobian of the residuals, and the speed of sound's share from refitting
    # paths scaled by 1 + h: neither uses the kernel's algebra; then the arc's sag as documented.
    receivers = ring_receivers((47, 0, 1))
    sigma = np.full(6, SIGMA_PATH) * np.linspace(1.0, 1.5, 6)  # unequal weights
    relative_sigma_speed = 0.0035
    for cls, range_m in ((CORNER, 1.5), (EDGE, 0.8)):
        bearing = np.radians([4.0])
        paths = exact_paths(cls, receivers, range_m, bearing)

        def fit(measured, edge=cls == EDGE):
            result = geometric_consistency(np.zeros(2), receivers[None], measured, sigma[None], covariances=True,
                                           relative_sigma_speed=relative_sigma_speed)
            return result, (result.edge_position if edge else result.virtual_image)[0]

        result, point = fit(paths)

        def residuals(at, edge=cls == EDGE, measured=paths[0]):
            emitter = np.linalg.norm(at) if edge else 0.0
            return (emitter + np.linalg.norm(at - receivers, axis=-1) - measured) / sigma

        step = 1e-7
        jacobian = np.stack([(residuals(point + step * e) - residuals(point - step * e)) / (2 * step)
                             for e in np.eye(2)], axis=1)
        shift = (fit(paths * (1 + 1e-6))[1] - fit(paths * (1 - 1e-6))[1]) / 2e-6
        expected = np.linalg.inv(jacobian.T @ jacobian) + relative_sigma_speed ** 2 * np.outer(shift, shift)
        # The arc's second-order spread along the line of sight from the equal-path circle's centre.
        centre = receivers.mean(axis=0) / (2 if cls == EDGE else 1)  # the emitter at the origin
        along = (point - centre) / np.linalg.norm(point - centre)
        across = np.array([-along[1], along[0]])
        expected += (SAG_BAND * (across @ expected @ across) ** 2 / np.sum((point - centre) ** 2)
                     * np.outer(along, along))
        covariance = result.edge_covariance if cls == EDGE else result.image_covariance
        assert_allclose(covariance[0], expected, rtol=1e-5)


def test_joint_fit_covariance_holds_the_spread_of_noisy_fits():
    # 2000 noisy echoes of a corner 1.5 m away heard by three pairs (sigma_t = 0.3 us): the fits scatter as
    # their reported covariance says (normalised errors' mean about 2, the 2-D chi-square's), 3 sigma holds.
    rng = np.random.default_rng(11)
    receivers = ring_receivers((47, 0, 1))
    trials, sigma = 2000, SPEED * 0.3e-6
    truth = 1.5 * np.array([np.cos(0.05), np.sin(0.05)])
    paths = exact_paths(CORNER, receivers, 1.5, np.full(trials, 0.05)) + rng.normal(0, sigma, (trials, 6))
    result = geometric_consistency(np.zeros(2), np.broadcast_to(receivers, (trials, 6, 2)), paths, sigma,
                                   covariances=True)
    error = 0.5 * result.virtual_image - truth  # the corner (T + T') / 2, T at the origin
    normalised = np.einsum("ni,nij,nj->n", error, np.linalg.inv(0.25 * result.image_covariance), error)
    assert 1.85 < normalised.mean() < 2.15
    assert np.mean(normalised <= CHI2_3_SIGMA) > 0.99
    assert_allclose(np.cov(error.T), 0.25 * result.image_covariance.mean(axis=0), rtol=0.1)


def test_joint_fit_covariance_holds_a_far_corners_sag_within_its_3_sigma_ellipse():
    # 4000 noisy echoes of a corner 4 m away heard by two pairs (sigma_t = 2 us): the fits scatter 46 mm across
    # the line of sight (standard deviation) and sag along it by up to 1.8 mm (99th percentile), four times their
    # whole spread along it (0.43 mm).  The ellipse must still hold a Gaussian's share, 99.73 % (99.5 %: 3
    # binomial standard deviations of 4000 trials below it; a band whose own 3 sigma held the sag alone held
    # 99.02 %).
    rng = np.random.default_rng(11)
    receivers = ring_receivers((0, 1))
    trials, sigma = 4000, SPEED * 2e-6
    truth = 4.0 * np.array([np.cos(0.05), np.sin(0.05)])
    paths = exact_paths(CORNER, receivers, 4.0, np.full(trials, 0.05)) + rng.normal(0, sigma, (trials, 4))
    result = geometric_consistency(np.zeros(2), np.broadcast_to(receivers, (trials, 4, 2)), paths, sigma,
                                   covariances=True)
    error = 0.5 * result.virtual_image - truth
    normalised = np.einsum("ni,nij,nj->n", error, np.linalg.inv(0.25 * result.image_covariance), error)
    assert np.mean(normalised <= CHI2_3_SIGMA) >= 0.995


def test_ring_consistency_says_which_rows_each_fit_joined():
    ring = load_layout("browne_ring")
    scene = load_scene("room")
    ping = Simulator(scene, ring).ping(scene.sensor_pose, noise=Noise(tof=1e-6), rng=np.random.default_rng(3))
    result = ring_consistency(ring, ping.group, ping.tof * ping.speed_of_sound, SIGMA_PATH, covariances=True)
    without = ring_consistency(ring, ping.group, ping.tof * ping.speed_of_sound, SIGMA_PATH)
    assert np.isnan(without.image_covariance).all() and np.isnan(without.edge_covariance).all()
    assert_array_equal(without.virtual_image, result.virtual_image)  # the same fits, without their covariances
    assert result.joined.shape == (ping.n_echoes, 5)  # its own and two overlapping groups on either side
    assert_array_equal(result.joined[:, 0], np.arange(ping.n_echoes))
    neighbours = overlapping_groups(ring)
    heard = np.isfinite(ping.tof).sum(axis=1)
    for row, rows in enumerate(result.joined):
        others = rows[1:][rows[1:] >= 0]
        assert np.isin(ping.group[others], neighbours[ping.group[row]]).all()
        if result.dof[row] >= 1:  # the fit used every receiver of the rows it joined
            assert result.dof[row] + 2 == heard[rows[rows >= 0]].sum()
            fits = result.chi2_specular[row] <= _chi2_upper_quantile(result.dof[row], CONSISTENCY_Z)
            assert np.isfinite(result.image_covariance[row]).all() == fits
    assert np.count_nonzero(result.dof >= 1) > ping.n_echoes // 2


def test_consistency_abstains_when_neither_model_fits():
    receivers = ring_receivers((0, 1))
    paths = exact_paths(PLANE, receivers, 0.5, np.radians([2.0]))
    paths[0, 3] += 0.05  # one receiver heard something else, 5 cm further
    result = geometric_consistency(np.zeros(2), receivers[None], paths, SIGMA_PATH, covariances=True)
    assert result.cls[0] == UNKNOWN and not result.specular[0]
    assert result.confidence[0] == 0.0 and result.margin[0] == 0.0
    assert result.chi2_specular[0] > 1e3 and result.chi2_edge[0] > 1e3
    assert np.isnan(result.image_covariance).all() and np.isnan(result.edge_covariance).all()  # no fit to trust


def test_overlapping_groups_of_the_ring_are_two_on_each_side():
    ring = load_layout("browne_ring")
    neighbours = overlapping_groups(ring)  # facings 7.5 deg apart, +-10 deg acceptance
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
    result = ring_consistency(triad, np.zeros(3, int), paths, 343.0 * 0.33e-6)
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
    together = ring_consistency(ring, np.concatenate([ping.group, flooded_group]),
                                         np.concatenate([paths, flooded_paths]), SIGMA_PATH)
    alone = ring_consistency(ring, ping.group, paths, SIGMA_PATH)
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
        ring_consistency(load_layout("barshan_kuc_pair"), [0], np.ones((1, 2)), SIGMA_PATH)
    ring_layout = load_layout("browne_ring")
    for group in (48, -1):
        with pytest.raises(ValueError, match=rf"group indices must be in \[0, 48\), got {group} in row 1"):
            ring_consistency(ring_layout, [0, group], np.ones((2, 2)), SIGMA_PATH)
    for sigma_path in (np.nan, -SIGMA_PATH, "wide", [SIGMA_PATH, SIGMA_PATH]):
        with pytest.raises(ValueError, match="sigma_path must be a finite number > 0"):
            ring_consistency(ring_layout, [0], np.ones((1, 2)), sigma_path)
    with pytest.raises(ValueError, match="paths"):
        ring_consistency(ring_layout, [0], np.ones((1, 3)), SIGMA_PATH)
    for z in (0.0, np.nan, [3.5, 3.5], "3.5", None, np.array("3.5"), 3.5j):
        with pytest.raises(ValueError, match="z must"):
            ring_consistency(ring_layout, [0], np.ones((1, 2)), SIGMA_PATH, z=z)
    for speed in (-0.01, np.nan, np.inf, "0.01", [0.01]):
        with pytest.raises(ValueError, match="relative_sigma_speed must be a finite number >= 0"):
            ring_consistency(ring_layout, [0], np.ones((1, 2)), SIGMA_PATH, relative_sigma_speed=speed)
        with pytest.raises(ValueError, match="relative_sigma_speed must be a finite number >= 0"):
            geometric_consistency(np.zeros(2), receivers, np.ones((2, 3)), SIGMA_PATH, relative_sigma_speed=speed)

    # ... bad data values give UNKNOWN / NaN, never an exception.
    ring = ring_receivers((0, 1))
    paths = exact_paths(EDGE, ring, 0.5, np.radians([1.0, 2.0, 3.0, 4.0]))
    paths[0, 1:] = np.nan  # one receiver left: nothing to test
    paths[1, :2] = np.nan  # two receivers: no redundancy
    paths[2, 0] = -1.0  # a negative path is dropped; three receivers remain
    transmitter = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [np.nan, 0.0]])
    with np.errstate(all="raise"):
        result = geometric_consistency(transmitter, np.broadcast_to(ring, (4, 4, 2)), paths, SIGMA_PATH,
                                       covariances=True)
    assert_array_equal(result.cls, [UNKNOWN, UNKNOWN, EDGE, UNKNOWN])
    assert_array_equal(result.dof, [-1, 0, 1, -2])
    assert_array_equal(result.confidence[[0, 1, 3]], 0.0)
    assert np.all(np.isnan(result.chi2_edge[[0, 1, 3]])) and np.all(np.isnan(result.virtual_image[[0, 1, 3]]))
    assert np.isnan(result.edge_covariance[[0, 1, 3]]).all() and np.isfinite(result.edge_covariance[2]).all()
    assert_array_equal(result.joined, np.arange(4)[:, None])
    # A ring ping with missing receivers, a path shorter than the height offset and no echoes at all.
    paths = np.array([[np.nan, np.nan], [0.05, 2.0], [2.0, np.inf]])
    with np.errstate(all="raise"):
        result = ring_consistency(ring_layout, [0, 1, 2], paths, SIGMA_PATH)
        empty = ring_consistency(ring_layout, np.zeros(0, int), np.zeros((0, 2)), SIGMA_PATH)
    assert_array_equal(result.cls, UNKNOWN)
    assert_array_equal(result.confidence, 0.0)
    assert empty.cls.shape == (0,) and empty.virtual_image.shape == (0, 2)
