"""Edge or corner by the wavefront's curvature: the two models' paths against a 50-digit reference, both models of
a sighting, the sequential test's false decisions over 10^4 simulated passes of a pure corner and a pure edge, a
point seen only head-on or from one place staying undecided, and the map deciding as the test does."""

import math

import mpmath
import numpy as np
import pytest
from numpy.testing import assert_allclose

from sonar_ring import localise, uncertainty
from sonar_ring.curvature import CURVATURE_THRESHOLD, PointModels, chi2_quantile, decide, point_models
from sonar_ring.geometry import load_layout
from sonar_ring.landmarks import CORNER, CORNER_OR_EDGE, EDGE, UNKNOWN, make_landmarks
from sonar_ring.mapping import LandmarkMap, transform_landmarks

RING = load_layout("browne_ring")
SPEED = 343.0
SEPARATION = 25.0  # the map's default min_separation


def pair_facing(angle):
    """The ring's emitter (origin) and the pair facing ``angle`` (rad), horizontal, sensor frame: (2,), (2,), (2,)."""
    plan = RING.plan
    group = int(np.argmin(np.abs(np.angle(np.exp(1j * (plan.yaw - angle))))))
    return plan.transmitters[group, 0], plan.receivers[group, 0], plan.receivers[group, 1]


def test_the_two_models_paths_against_a_50_digit_reference():
    mpmath.mp.dps = 50
    rng = np.random.default_rng(1)
    for _ in range(200):
        point = rng.uniform(-3, 3, 2)
        tx, rx1, rx2 = pair_facing(math.atan2(point[1], point[0]))
        for rx in (rx1, rx2):
            edge = np.linalg.norm(point - tx) + np.linalg.norm(point - rx)
            corner = np.linalg.norm(2 * point - tx - rx)
            p, t, r = ([mpmath.mpf(float(v)) for v in vector] for vector in (point, tx, rx))
            edge_ref = mpmath.sqrt((p[0] - t[0]) ** 2 + (p[1] - t[1]) ** 2) + mpmath.sqrt((p[0] - r[0]) ** 2
                                                                                       + (p[1] - r[1]) ** 2)
            corner_ref = mpmath.sqrt((2 * p[0] - t[0] - r[0]) ** 2 + (2 * p[1] - t[1] - r[1]) ** 2)
            assert abs(edge - float(edge_ref)) < 1e-14 and abs(corner - float(corner_ref)) < 1e-14
            # the second-order difference between them, which the test lives on, to 1e-15 m
            assert abs((edge - corner) - float(edge_ref - corner_ref)) < 1e-14
            # |a+b| + |a-b| <= 2 sqrt(|a|^2 + |b|^2): the edge's path exceeds the corner's by at most h^2 / d, with
            # h half the pair's separation and d the point's distance from its middle
            assert 0.0 <= float(edge_ref - corner_ref) <= np.sum((tx - rx) ** 2) / (2 * corner) * (1 + 1e-12)


def test_point_models_solve_both_models_from_the_paths_a_landmark_implies():
    corner_point, edge_point = np.array([1.2, 0.9]), np.array([-0.4, 2.1])
    paths_covariance = (SPEED * 1e-6) ** 2 * np.eye(2)
    rows = []
    for point, model in ((corner_point, localise.corner), (edge_point, localise.edge)):
        tx, rx1, rx2 = pair_facing(math.atan2(point[1], point[0]))
        paths = [np.linalg.norm(2 * point - tx - rx) if model is localise.corner
                 else np.linalg.norm(point - tx) + np.linalg.norm(point - rx) for rx in (rx1, rx2)]
        estimates = [solve(tx, rx1, rx2, *paths) for solve in (localise.corner, localise.edge)]
        covariances = [uncertainty.position_covariance(estimate, tx, rx1, rx2, paths_covariance)
                       for estimate in estimates]
        group = int(np.argmin(np.abs(np.angle(np.exp(1j * (RING.plan.yaw - math.atan2(point[1], point[0])))))))
        rows.append((estimates, covariances, group, 0.5 * (tx + 0.5 * (rx1 + rx2))))
    # what classify_ping hands on: an undecided point by the virtual-image model, its covariance widened by the
    # models' discrepancy g g^T; an edge by the edge model
    gap = rows[0][0][1].position - rows[0][0][0].position
    landmarks = make_landmarks([UNKNOWN, EDGE], [rows[0][0][0].position, rows[1][0][1].position],
                               group=[rows[0][2], rows[1][2]],
                               covariance=[rows[0][1][0] + np.outer(gap, gap), rows[1][1][1]])
    models = point_models(RING, landmarks)
    assert models.valid.all()
    assert_allclose(models.corner[0], corner_point, atol=1e-12)  # the corner's own model: exact
    assert_allclose(models.edge[1], edge_point, atol=1e-12)
    # the other model of the same paths: a few millimetres across the line of sight, a fraction of one along it
    for row, point in ((0, corner_point), (1, edge_point)):
        gap = models.edge[row] - models.corner[row]
        sight = point / np.linalg.norm(point)
        assert 1e-4 < abs(sight[0] * gap[1] - sight[1] * gap[0]) < 0.05 and abs(sight @ gap) < 5e-4
    # each model's covariance from the paths' (the discrepancy taken off), with the arc's spread
    for row, (estimates, covariances, _, centre) in enumerate(rows):
        for position, covariance, estimate, first_order in ((models.corner[row], models.corner_covariance[row],
                                                             estimates[0], covariances[0]),
                                                            (models.edge[row], models.edge_covariance[row],
                                                             estimates[1], covariances[1])):
            # the arc's spread: variance s^4 / (2 r^2) and squared mean s^4 / (4 r^2) along the line of sight
            sight = estimate.position - centre
            along = sight / np.linalg.norm(sight)
            across = np.array([-along[1], along[0]])
            spread = 0.75 * (across @ first_order @ across) ** 2 / (sight @ sight)
            assert_allclose(covariance, first_order + spread * np.outer(along, along), rtol=1e-6, atol=1e-15)
            assert_allclose(position, estimate.position, atol=1e-12)
    assert np.all(models.separation_noise > 0) and np.all(models.separation_noise < 1)
    assert not point_models(load_layout("kreczmer_triad"), landmarks).valid.any()


def passes(kind, runs, rng, sigma_tof=1e-6, pings=120, motion="past"):
    """Both point models (:func:`point_models`, map frame) of one reflector's sightings per run, from a robot driving
    3 m past it along x (``motion="past"``), 1.8 m straight at it along y (``"head-on"``) or standing still:
    positions (R, n, 2), covariances (R, n, 2, 2), separation noise (R, n), and the robot's travel (n,) m."""
    sigma = SPEED * sigma_tof
    x0 = np.zeros(runs) if motion == "head-on" else rng.uniform(-0.5, 0.5, runs)
    y0 = rng.uniform(2.5, 3.0, runs) if motion == "head-on" else rng.uniform(0.8, 2.5, runs)
    travel = {"past": np.linspace(-1.5, 1.5, pings), "head-on": np.linspace(0.0, 1.8, pings),
              "standing": np.zeros(pings)}[motion]
    along = np.array([0.0, 1.0]) if motion == "head-on" else np.array([1.0, 0.0])
    paths_covariance = np.tile(sigma ** 2 * np.eye(2), (runs, 1, 1))
    seen = []
    for s in travel:
        point = np.stack([x0, y0], -1) - s * along  # sensor frame (yaw 0)
        angle = np.arctan2(point[:, 1], point[:, 0])
        groups = np.argmin(np.abs(np.angle(np.exp(1j * (RING.plan.yaw[None, :] - angle[:, None])))), axis=1)
        tx, rx = RING.plan.transmitters[groups, 0], RING.plan.receivers[groups]
        if kind == "corner":
            true = np.linalg.norm(2 * point[:, None] - tx[:, None] - rx, axis=-1)
        else:
            true = np.linalg.norm(point - tx, axis=-1)[:, None] + np.linalg.norm(point[:, None] - rx, axis=-1)
        noisy = true + rng.normal(0.0, sigma, true.shape)
        # what classify_ping hands on: the virtual-image model's position, its covariance, the pair
        estimate = localise.corner(tx, rx[:, 0], rx[:, 1], noisy[:, 0], noisy[:, 1])
        landmarks = make_landmarks(np.full(runs, CORNER), estimate.position, group=groups, covariance=(
            uncertainty.position_covariance(estimate, tx, rx[:, 0], rx[:, 1], paths_covariance)))
        seen.append(point_models(RING, landmarks).transformed((*(s * along), 0.0)))
    return (np.stack([m.corner for m in seen], 1), np.stack([m.edge for m in seen], 1),
            np.stack([m.corner_covariance for m in seen], 1), np.stack([m.edge_covariance for m in seen], 1),
            np.stack([m.separation_noise for m in seen], 1), travel)


def running_chi2(values, covariance, noise=0.0):
    """The residual sum of a constant fit to each run's first 1..n values (R, n, 2), given their covariance."""
    weight = np.linalg.inv(covariance)
    inverse = np.linalg.inv(np.cumsum(weight, axis=1))
    pulled = np.cumsum(np.einsum("rnij,rnj->rni", weight, values), axis=1)
    square = np.cumsum(np.einsum("rni,rnij,rnj->rn", values, weight, values) - noise, axis=1)
    return square - np.einsum("rni,rnij,rnj->rn", pulled, inverse, pulled)


def sequential(corner, edge, corner_covariance, edge_covariance, separation_noise, threshold=CURVATURE_THRESHOLD):
    """The map's sequential test on each run's sightings in order: the class it ends with, the sighting deciding."""
    separation = running_chi2(edge - corner, corner_covariance, separation_noise)
    sightings = np.arange(1, corner.shape[1] + 1)[None, :]
    is_edge, is_corner, _ = decide(running_chi2(corner, corner_covariance), running_chi2(edge, edge_covariance),
                                   separation, sightings, threshold, SEPARATION)
    decided = is_edge | is_corner
    first = np.where(decided.any(axis=1), np.argmax(decided, axis=1), -1)
    rows = np.arange(corner.shape[0])
    verdict = np.where(first < 0, CORNER_OR_EDGE, np.where(is_edge[rows, first], EDGE, CORNER))
    return verdict, first


@pytest.mark.parametrize("kind", ["corner", "edge"])
def test_the_sequential_test_is_wrong_at_most_once_in_a_thousand(kind):
    rng = np.random.default_rng(2024 if kind == "corner" else 2025)
    verdicts, separations = [], []
    for _ in range(5):  # 5 x 2000 = 10^4 passes
        corner, edge, corner_covariance, edge_covariance, noise, _ = passes(kind, 2000, rng)
        verdicts.append(sequential(corner, edge, corner_covariance, edge_covariance, noise)[0])
        separations.append(running_chi2(edge - corner, corner_covariance, noise)[:, -1])
    verdict, separation = np.concatenate(verdicts), np.concatenate(separations)
    right, wrong = (CORNER, EDGE) if kind == "corner" else (EDGE, CORNER)
    assert verdict.size == 10_000
    assert np.count_nonzero(verdict == wrong) <= 10, np.count_nonzero(verdict == wrong)
    # A 3 m pass at 0.8-2.5 m offers the separation the test needs (lambda >= 25) in one run of ten (corner) to
    # one of six (edge) at 1 us: those decide, and right.
    strong = separation >= SEPARATION
    assert strong.sum() >= 500
    assert np.mean(verdict[strong] == right) >= 0.98


@pytest.mark.parametrize("motion", ["head-on", "standing"])
def test_a_point_seen_only_head_on_or_from_one_place_stays_undecided(motion):
    # Driving straight at it, the ring's facing pair, its emitter and the point stay (nearly) collinear: the two
    # models agree to micrometres; standing, no viewpoint is new. However many pings: no guess.
    rng = np.random.default_rng(3)
    for kind in ("corner", "edge"):
        verdict, _ = sequential(*passes(kind, 1000, rng, motion=motion)[:5])
        assert np.all(verdict == CORNER_OR_EDGE)


def test_the_map_decides_as_the_sequential_test():
    rng = np.random.default_rng(4)
    for kind, expected in (("corner", CORNER), ("edge", EDGE)):
        corner, edge, corner_covariance, edge_covariance, noise, travel = passes(kind, 200, rng)
        verdict, first = sequential(corner, edge, corner_covariance, edge_covariance, noise)
        separation = running_chi2(edge - corner, corner_covariance, noise)[:, -1]
        # two runs the pass decides with sightings to spare, one it leaves far from deciding (the map may drop a
        # sighting its gate refuses: a run on the brink could go either way)
        runs = [*np.flatnonzero((verdict == expected) & (first < 100))[:2],
                np.flatnonzero((verdict == CORNER_OR_EDGE) & (separation < 15))[0]]
        for run in runs:
            landmark_map = LandmarkMap()
            for j, s in enumerate(travel):
                sensor = np.array([s, 0.0, 0.0])
                gap = edge[run, j] - corner[run, j]  # as classify_ping widens an undecided point's covariance
                seen = make_landmarks([UNKNOWN], corner[run, j] - sensor[:2],
                                      covariance=corner_covariance[run, j] + np.outer(gap, gap))
                models = PointModels(corner[run, j][None], edge[run, j][None], corner_covariance[run, j][None],
                                     edge_covariance[run, j][None], noise[run, j][None], np.ones(1, bool))
                landmark_map.update(transform_landmarks(seen, sensor), sensor, models)
            assert landmark_map.snapshot().landmark_class.tolist() == [verdict[run]], (kind, run)
            # the distance driven from the first sighting to the decision: the sequential test's deciding sighting
            expected_distance = [travel[first[run]] - travel[0]] if verdict[run] != CORNER_OR_EDGE else []
            assert_allclose(landmark_map.decision_distances(), expected_distance, atol=1e-9)
            # what the mapper publishes: a point its curvature can tell is held back until it does
            published = landmark_map.snapshot(decided=True).landmark_class.tolist()
            assert published == ([] if verdict[run] == CORNER_OR_EDGE else [verdict[run]]), (kind, run)
            assert landmark_map.decided(landmark_map.entries().uid).tolist() == [verdict[run] != CORNER_OR_EDGE]


def test_chi2_quantile_is_wilson_hilferty():
    scipy_stats = pytest.importorskip("scipy.stats")
    for dof in (2, 10, 100, 1000):
        assert chi2_quantile(dof, 3.0902) == pytest.approx(scipy_stats.chi2.ppf(0.999, dof), rel=0.025)
